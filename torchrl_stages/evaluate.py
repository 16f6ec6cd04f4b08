"""Greedy rollouts and their episode statistics (stage-level and whole-task)."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch.nn.functional import one_hot
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_stages.handoff import Handoffs, collect_handoffs
from torchrl_stages.preemption import stop_if_asked
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import SUCCESS_KEY, StageTransform

if TYPE_CHECKING:
    from torchrl_stages.task import StagedTask

CHUNK = 250  # whole-task episodes per batched rollout (bounds the memory of long rollouts)


def can_step_finished(env: EnvBase) -> bool:
    """Whether :func:`rollout_first_episodes` may step ``env``'s finished elements on: its
    class declares ``can_step_finished``, true, under StageTransforms only."""
    if isinstance(env, TransformedEnv):  # torchrl unwraps nested TransformedEnvs into one
        parts = env.transform.transforms if isinstance(env.transform, Compose) else [env.transform]
        if not all(isinstance(t, StageTransform) for t in parts):
            return False
        env = env.base_env
    # declared by the env's own class: batched envs and wrappers forward unknown attributes
    declared = inspect.getattr_static(type(env), "can_step_finished", None) is not None
    return declared and env.can_step_finished is True


@torch.no_grad()
def rollout_first_episodes(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int
) -> TensorDictBase:
    """Greedy rollout ``[*batch, T <= max_steps]`` until every element has ended one episode;
    finished elements are reset, or step on where :func:`can_step_finished` (no reset cost)."""
    steps = []
    finished = torch.zeros(env.batch_size, dtype=torch.bool, device=env.device)
    reset_finished = not can_step_finished(env)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        for _ in range(max_steps):
            td = policy(td)
            if reset_finished:
                td, td_next = env.step_and_maybe_reset(td)
            else:  # step_and_maybe_reset without the reset (torchrl's rollout does the same)
                td = env.step(td)
                td_next = env._step_mdp(td)
                if env._post_step_mdp_hooks is not None:
                    td, td_next = env._post_step_mdp_hooks(td, td_next)
            steps.append(td)
            finished |= td.get(("next", "done")).reshape(env.batch_size)
            if finished.all():
                break
            td = td_next
    return torch.stack(steps, dim=-1)


def ended_well(td: TensorDictBase) -> torch.Tensor:
    """Whether each step of ``td`` would end its episode solved: the env's ``("next",
    "success")`` flag where it writes one, else ``terminated`` (tasks that end only on success)."""
    flag = td.get(("next", SUCCESS_KEY), None)
    return td.get(("next", "terminated")) if flag is None else flag.to(torch.bool)


class EpisodeStats(NamedTuple):
    """Each batch element's first episode in a rollout."""

    success: torch.Tensor  # bool [B]: solved (ended_well) on its last step, not unfinished
    length: torch.Tensor  # int64 [B]: steps of the first episode
    ret: torch.Tensor  # float [B]: undiscounted return of the first episode

    def summary(self) -> dict[str, float | None]:
        """Success rate, mean return and steps; steps of successes (``None`` without any)."""
        ok = self.success
        steps = self.length[ok].float()
        return {
            "success_rate": ok.float().mean().item(),
            "mean_return": self.ret.mean().item(),
            "mean_steps": self.length.float().mean().item(),
            "mean_steps_success": steps.mean().item() if ok.any() else None,
            "median_steps_success": steps.quantile(0.5).item() if ok.any() else None,
        }

    @classmethod
    def cat(cls, parts: list[EpisodeStats]) -> EpisodeStats:
        return cls(*map(torch.cat, zip(*parts, strict=True)))


def episode_stats(rollout: TensorDictBase) -> EpisodeStats:
    """The :class:`EpisodeStats` of a ``[B, T]`` rollout."""
    done = rollout.get(("next", "done")).squeeze(-1)  # [B, T]
    solved = ended_well(rollout).squeeze(-1)
    reward = rollout.get(("next", "reward")).squeeze(-1)
    T = done.shape[-1]
    any_done = done.any(-1)
    first = torch.where(any_done, done.float().argmax(-1), T - 1)  # the first episode's last step
    in_first = torch.arange(T, device=done.device) <= first.unsqueeze(-1)
    success = any_done & solved.gather(-1, first.unsqueeze(-1)).squeeze(-1)
    return EpisodeStats(success=success, length=first + 1, ret=(reward * in_first).sum(-1))


def discounted_return(
    rollout: TensorDictBase, length: torch.Tensor, gamma: float | Sequence[float]
) -> torch.Tensor:
    """``sum_t w_t r_t`` over each row's first ``length`` steps, ``w_t = gamma^t`` or, one gamma
    per stage, ``prod_{j<t} gamma[stage(s_j)]`` (the merged return of Proposition 1)."""
    reward = rollout.get(("next", "reward")).squeeze(-1)  # [B, T]
    steps = torch.arange(reward.shape[-1], device=reward.device)
    if isinstance(gamma, int | float):
        weights = gamma ** steps.to(reward.dtype)
    else:
        per_step = torch.as_tensor(gamma, dtype=reward.dtype, device=reward.device)
        per_step = per_step[rollout.get("stage").squeeze(-1)]  # [B, T]: gamma of s_t
        weights = torch.cumprod(per_step, -1) / per_step  # prod_{j<t} gamma_j
    weights = torch.where(steps < length.unsqueeze(-1), weights, 0.0)
    return (reward * weights).sum(-1)


def evaluate_policy(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int
) -> tuple[EpisodeStats, TensorDictBase]:
    """Greedy first-episode statistics of ``policy`` on ``env``, and the rollout itself."""
    keep_threads()  # a batched env closed since (a task report's, a chunk's) may have changed it
    rollout = rollout_first_episodes(env, policy, max_steps)
    return episode_stats(rollout), rollout


@torch.no_grad()
def evaluate_greedy(
    env: EnvBase,
    policy: TensorDictModuleBase,
    value: TensorDictModuleBase,
    max_steps: int,
    gamma: float | Sequence[float],
    reduce: str = "mean",
    *,
    groups: int = 1,
) -> list[dict[str, float]]:
    """A loop's evaluation: one summary per equal part of ``env``'s batch (one per seed), with
    the mean ``discounted_return`` G and ``value_error`` ``|V(s_0) - G|`` (``reduce``: mean|max)."""
    stats, rollout = evaluate_policy(env, policy, max_steps)
    returns = discounted_return(rollout, stats.length, gamma)
    v0 = value(rollout[:, 0].clone()).get("state_value").reshape(-1)
    columns = (*stats, (v0 - returns).abs(), returns)
    summaries = []
    for ok, length, ret, err, g in zip(*(c.tensor_split(groups) for c in columns), strict=True):
        summary = EpisodeStats(ok, length, ret).summary()
        summary["value_error"] = (err.max() if reduce == "max" else err.mean()).item()
        summary["discounted_return"] = g.mean().item()
        summaries.append(summary)
    return summaries


class TaskEvaluation(NamedTuple):
    """Greedy whole-task episodes of a stacked policy (the first episode of every batch row)."""

    stats: EpisodeStats
    steps_per_stage: torch.Tensor  # int64 [E, N]: the steps each episode spent in each stage
    final: TensorDictBase  # the "next" content of every episode's last step [E]
    rollout: TensorDictBase  # the first chunk's rollout, for figures
    starts: str  # "all" (every start state once), else "fixed" (one start for all) or "random"
    handoffs: list[Handoffs]  # per boundary k -> k+1

    def summary(self) -> dict[str, Any]:
        """The numbers ``eval.json`` reports for every task."""
        return {
            "episodes": len(self.stats.length),
            "starts": self.starts,
            **self.stats.summary(),
            "mean_steps_per_stage": self.steps_per_stage.float().mean(0).tolist(),
        }


@torch.no_grad()
def evaluate_task(
    task: StagedTask,
    policy: TensorDictModuleBase,
    episodes: int,
    seed: int,
    *,
    interruptible: bool = False,
) -> TaskEvaluation:
    """Greedy whole-task episodes: one from every start state where the env lists them, else
    ``episodes`` random starts in chunks (``interruptible``: a signal stops it between chunks)."""
    all_starts = task.start_states(None) is not None
    sizes = [None] if all_starts else [min(CHUNK, episodes - i) for i in range(0, episodes, CHUNK)]
    chunks, per_stage, final, handoffs, first = [], [], [], [], None
    one_start = not all_starts
    gammas = [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]
    for i, size in enumerate(sizes):
        if interruptible:  # a resumed run evaluates again
            stop_if_asked("the whole-task evaluation")
        env = task.task_env(size)
        env.set_seed(seed + i)
        chunk, rollout = evaluate_policy(env, policy, int(getattr(env.base_env, "max_steps", 1000)))
        length = chunk.length
        in_episode = torch.arange(rollout.shape[-1], device=length.device) < length.unsqueeze(-1)
        stage = one_hot(rollout.get("stage").squeeze(-1), task.num_stages)
        per_stage.append((stage * in_episode.unsqueeze(-1)).sum(1))
        chunks.append(chunk)
        rows = torch.arange(rollout.shape[0], device=length.device)
        final.append(rollout.get("next")[rows, length - 1])
        handoffs.append(collect_handoffs(rollout, length, gammas))
        first = rollout if first is None else first
        if one_start:  # every episode so far starts from the first one's observation
            starts = rollout[:, 0].select(*env.observation_spec.keys(True, True), strict=False)
            one_start = all(
                torch.equal(value, first[0, 0].get(key).expand_as(value))
                for key, value in starts.items(True, True)
                if isinstance(value, torch.Tensor)
            )
    stats = EpisodeStats.cat(chunks)
    one_start = one_start and len(stats.length) > 1
    return TaskEvaluation(
        stats,
        torch.cat(per_stage),
        torch.cat(final),
        first,
        "all" if all_starts else "fixed" if one_start else "random",
        [Handoffs.cat(parts) for parts in zip(*handoffs, strict=True)],
    )
