"""Cargo-transport report: 1000 whole-task episodes, steps per robot, the Fig. 3 trajectories."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask

EPISODES = 1000
CHUNK = 250  # episodes per batched rollout (bounds the memory of 500-step rollouts)
EXAMPLES = 8  # trajectories drawn in cargo.png
SEED = 12345


def trajectories(rollout, length: torch.Tensor, count: int) -> list[tuple[list, list]]:
    """``(positions [T+1, 2], stages [T+1])`` of the first ``count`` rows' first episodes."""
    out = []
    for i in range(min(count, len(length))):
        n = int(length[i])
        positions = torch.cat([rollout["position"][i, :1], rollout["next", "position"][i, :n]])
        stages = torch.cat([rollout["stage"][i, :1], rollout["next", "stage"][i, :n]])
        out.append((positions.tolist(), stages.squeeze(-1).tolist()))
    return out


@torch.no_grad()
def evaluate_cargo(
    task: StagedTask, policy: StackedPolicy, episodes: int = EPISODES, seed: int = SEED
) -> tuple[dict[str, Any], list[tuple[list, list]]]:
    """Whole-task greedy episodes from random left-half starts, in chunks of :data:`CHUNK`.

    Returns the metrics (success rate; mean and median steps to the target over successful
    episodes; mean steps each robot carried the cargo) and :data:`EXAMPLES` trajectories.
    """
    success, length, per_stage, examples = [], [], [], []
    for start in range(0, episodes, CHUNK):
        env = task.task_env(min(CHUNK, episodes - start))
        env.set_seed(seed + start)
        stats, rollout = evaluate_policy(env, policy, env.base_env.max_steps)
        steps = torch.arange(rollout.shape[-1])
        in_episode = steps < stats.length.unsqueeze(-1)
        stage = rollout["stage"].squeeze(-1)
        per_stage.append(
            torch.stack([((stage == k) & in_episode).sum(-1) for k in range(task.num_stages)], -1)
        )
        success.append(stats.success)
        length.append(stats.length)
        if not examples:
            examples = trajectories(rollout, stats.length, EXAMPLES)
    ok, steps = torch.cat(success), torch.cat(length).float()
    metrics = {
        "episodes": episodes,
        "success_rate": ok.float().mean().item(),
        "mean_steps_success": steps[ok].mean().item() if ok.any() else None,
        "median_steps_success": steps[ok].median().item() if ok.any() else None,
        "mean_steps_per_robot": torch.cat(per_stage).float().mean(0).tolist(),
    }
    return metrics, examples


def report(
    task: StagedTask, learners: Sequence[Learner], run_dir: Path, plots: bool = True
) -> dict[str, Any]:
    """Cargo metrics for ``eval.json`` (and the Fig. 3 panel ``cargo.png`` when ``plots``)."""
    policy = StackedPolicy([learner.policy for learner in learners])
    metrics, examples = evaluate_cargo(task, policy)
    env = task.base_env(1)
    metrics["robots"] = list(env.robots)
    if plots:
        from torchrl_stages.plots import plot_cargo_figure

        plot_cargo_figure(
            env.occupancy.cpu().numpy(),
            examples,
            robots=env.robots,
            stage_line=env.stage_line,
            target=env.target,
            success_radius=env.success_radius,
            out=run_dir / "cargo.png",
            title=f"greedy stacked policy ({' -> '.join(env.robots)}), "
            f"success {metrics['success_rate']:.1%}",
        )
    return metrics
