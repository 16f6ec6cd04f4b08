"""Handoff diagnostics: at each boundary k -> k+1, how well ``V_{k+1}`` holds at the states where
stage k hands over, and whether they lie inside stage k+1's training starts."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from contextlib import closing
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from tensordict import TensorDictBase

if TYPE_CHECKING:
    from torchrl_stages.learners import Learner
    from torchrl_stages.task import StagedTask

log = logging.getLogger("torchrl_stages")

# the share of handoff states outside the starts that is warned about (drawn like them: 5%)
OUTSIDE_WARNING = 0.25
REFERENCE_STARTS, HELD_OUT_STARTS = 1024, 256


class Handoffs(NamedTuple):
    """The handoff states of one boundary k -> k+1 over a set of episodes."""

    states: TensorDictBase | None  # the first state of stage k+1 of each episode that reached it
    returns: torch.Tensor  # the stage-discounted return each episode obtained from it

    @classmethod
    def cat(cls, parts: Sequence[Handoffs]) -> Handoffs:
        states = [p.states for p in parts if p.states is not None and p.states.numel()]
        return cls(torch.cat(states) if states else None, torch.cat([p.returns for p in parts]))


@torch.no_grad()
def collect_handoffs(
    rollout: TensorDictBase, length: torch.Tensor, gammas: Sequence[float]
) -> list[Handoffs]:
    """The handoffs at each boundary of the first ``length`` steps of a ``[B, T]`` rollout."""
    stage = rollout.get("stage").squeeze(-1)  # [B, T]: stage of s_t
    nxt = rollout.get(("next", "stage")).squeeze(-1)
    reward = rollout.get(("next", "reward")).squeeze(-1).to(torch.float64)
    steps = torch.arange(stage.shape[-1], device=stage.device)
    in_episode = steps < length.unsqueeze(-1)
    g = torch.as_tensor(list(gammas), dtype=torch.float64, device=stage.device)[stage]
    cum = torch.cumprod(g, -1)  # prod_{i<=t} gamma(s_i)
    out = []
    for k in range(len(gammas) - 1):
        crossing = (stage == k) & (nxt == k + 1) & in_episode
        rows = crossing.any(-1).nonzero().squeeze(-1)
        t = crossing.float().argmax(-1)[rows]  # the step that leaves stage k
        # the return from s' = s_{t+1}: sum_{j>t} r_j prod_{t<i<j} gamma(s_i)
        weights = cum[rows] / g[rows] / cum[rows, t].unsqueeze(-1)  # prod_{i<j} / prod_{i<=t}
        after = (steps > t.unsqueeze(-1)) & in_episode[rows]
        returns = (reward[rows] * torch.where(after, weights, 0.0)).sum(-1)
        states = rollout.get("next")[rows, t].exclude("reward", "done", "terminated", "truncated")
        out.append(Handoffs(states if len(rows) else None, returns))
    return out


def _features(td: TensorDictBase, keys: Sequence[Any]) -> torch.Tensor:
    return torch.cat([td.get(key).reshape(td.shape[0], -1).to(torch.float64) for key in keys], -1)


@torch.no_grad()
def handoff_diagnostics(
    task: StagedTask, learners: Sequence[Learner], handoffs: Sequence[Handoffs], seed: int
) -> list[dict[str, Any]]:
    """One record per boundary (``eval.json``'s ``"handoff"``): ``|V_{k+1}(s') - G|`` at the
    handoff states and their distance to stage k+1's training starts (a warning where they lie
    outside them)."""
    records = []
    for k, handoff in enumerate(handoffs):
        name = f"{task.stage_names[k]} -> {task.stage_names[k + 1]}"
        record: dict[str, Any] = {"boundary": name, "stage": k, "episodes": 0}
        records.append(record)
        if handoff.states is None:
            continue
        states = handoff.states.clone().to(task.device)
        v = learners[k + 1].value()(states).get("state_value").reshape(-1).to(torch.float64).cpu()
        g = handoff.returns.cpu()
        error = (v - g).abs()
        record.update(
            episodes=len(g),
            value_error_mean=error.mean().item(),
            value_error_max=error.max().item(),
            value_bias=(v - g).mean().item(),
            values=v.tolist(),
            returns=g.tolist(),
        )
        if task.stage_starts:
            record.update(_distance_to_starts(task, k + 1, handoff.states, seed))
        if record.get("extrapolated"):
            log.warning(
                f"handoff {name}: {100 * record['outside_starts']:.0f}% of the states stage {k} "
                f"hands over lie outside stage {k + 1}'s training starts, where its value is "
                f"extrapolated (|V - G| {record['value_error_mean']:.3g} on average). Fix: make "
                f"the env's start_stage={k + 1} starts cover where stage {k} arrives"
            )
    return records


def _distance_to_starts(
    task: StagedTask, stage: int, states: TensorDictBase, seed: int
) -> dict[str, Any]:
    """The distance of ``states`` to their nearest start, in observations standardized by the
    starts' spread; outside the starts beyond the 95% quantile of held-out starts' distances."""
    keys = task.specs(stage).observation_keys
    wanted = REFERENCE_STARTS + HELD_OUT_STARTS
    # the stage's own training batch, reset until enough starts are drawn (a vector env of
    # worker processes is never built a thousand wide)
    drawn = []
    with closing(task.base_env(int(task.stage_cfg(stage).num_envs), start_stage=stage)) as env:
        env.set_seed(seed)
        while sum(map(len, drawn)) < wanted:
            drawn.append(_features(env.reset().reshape(-1).cpu(), keys))
    feats = torch.cat(drawn)[:wanted]
    mean, std = feats[:REFERENCE_STARTS].mean(0), feats[:REFERENCE_STARTS].std(0).clamp_min(1e-6)
    ref, held_out = ((feats - mean) / std).split([REFERENCE_STARTS, HELD_OUT_STARTS])
    handed = (_features(states.cpu(), keys) - mean) / std
    threshold = torch.quantile(torch.cdist(held_out, ref).min(-1).values, 0.95)
    distance = torch.cdist(handed, ref).min(-1).values
    # distances that differ by float rounding only (discrete starts: 0 and ~1e-8) are equal
    outside = (distance > threshold * (1 + 1e-6) + 1e-6).double().mean().item()
    return {
        "start_distance_median": distance.median().item(),
        "start_distance_threshold": threshold.item(),
        "outside_starts": outside,
        "extrapolated": outside > OUTSIDE_WARNING,
    }


def plot_handoffs(records: Sequence[dict[str, Any]], out: str | Path) -> Path | None:
    """``handoff.png``: per boundary, ``V_{k+1}(s')`` against the return obtained after it."""
    shown = [r for r in records if r.get("episodes")]
    if not shown:
        return None
    from matplotlib.figure import Figure

    from torchrl_stages.plots import save_figure

    fig = Figure(figsize=(3.2 * len(shown), 3.4))
    for ax, r in zip(fig.subplots(1, len(shown), squeeze=False)[0], shown, strict=True):
        g, v = r["returns"], r["values"]
        ax.scatter(g, v, s=10, alpha=0.5, color="tab:red" if r.get("extrapolated") else "tab:blue")
        low, high = min(min(g), min(v)), max(max(g), max(v))
        pad = 0.05 * (high - low or 1.0)
        ax.plot([low - pad, high + pad], [low - pad, high + pad], color="gray", lw=0.8)
        outside = f", {r['outside_starts']:.0%} outside starts" if "outside_starts" in r else ""
        ax.set_title(f"{r['boundary']}\n|V-G| {r['value_error_mean']:.3f}{outside}", fontsize=9)
        ax.set_xlabel("return after the handoff")
    fig.axes[0].set_ylabel("V of the next stage")
    fig.tight_layout()
    return save_figure(fig, out)
