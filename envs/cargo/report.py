"""Cargo-transport report: the robots and the Fig. 3 trajectories of the run's evaluation."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

from torchrl_stages.evaluate import TaskEvaluation
from torchrl_stages.learners import Learner
from torchrl_stages.task import StagedTask

EXAMPLES = 8  # trajectories drawn in cargo.png


def trajectories(
    rollout: TensorDictBase, length: torch.Tensor, count: int
) -> list[tuple[list, list]]:
    """``(positions [T+1, 2], stages [T+1])`` of the first ``count`` rows' first episodes."""
    out = []
    for i in range(min(count, len(length))):
        n = int(length[i])
        positions = torch.cat([rollout["position"][i, :1], rollout["next", "position"][i, :n]])
        stages = torch.cat([rollout["stage"][i, :1], rollout["next", "stage"][i, :n]])
        out.append((positions.tolist(), stages.squeeze(-1).tolist()))
    return out


def report(
    task: StagedTask,
    learners: Sequence[Learner],
    evaluation: TaskEvaluation,
    run_dir: Path,
    plots: bool = True,
) -> dict[str, Any]:
    """The robots of each stage for ``eval.json`` (the steps each one carried the cargo are the
    evaluation's ``mean_steps_per_stage``), and the Fig. 3 panel ``cargo.png`` when ``plots``."""
    env = task.base_env(1)
    if plots:
        from .figures import plot_cargo_figure

        success = evaluation.stats.success.float().mean().item()
        plot_cargo_figure(
            env.occupancy.cpu().numpy(),
            trajectories(evaluation.rollout, evaluation.stats.length, EXAMPLES),
            robots=env.robots,
            stage_line=env.stage_line,
            target=env.target,
            success_radius=env.success_radius,
            out=run_dir / "cargo.png",
            title=f"greedy stacked policy ({' -> '.join(env.robots)}), success {success:.1%}",
        )
    return {"robots": list(env.robots)}
