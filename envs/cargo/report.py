"""Cargo-transport report: the robots and the Fig. 3 trajectories of the run's evaluation."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchrl_stages.evaluate import TaskEvaluation
from torchrl_stages.learners import Learner
from torchrl_stages.task import StagedTask

from .._common import episode_path

EXAMPLES = 8  # trajectories drawn in cargo.png


def report(
    task: StagedTask,
    learners: Sequence[Learner],
    evaluation: TaskEvaluation,
    run_dir: Path,
    plots: bool = True,
) -> dict[str, Any]:
    """The robots of each stage (the steps each carried the cargo are the evaluation's
    ``mean_steps_per_stage``), and the Fig. 3 panel ``cargo.png`` when ``plots``."""
    env = task.base_env(1)
    if plots:
        from .figures import plot_cargo_figure

        rollout, length = evaluation.rollout, evaluation.stats.length.tolist()
        trajectories = [
            (
                episode_path(rollout, "position", i, n).tolist(),
                episode_path(rollout, "stage", i, n).squeeze(-1).tolist(),
            )
            for i, n in enumerate(length[:EXAMPLES])
        ]
        success = evaluation.stats.success.float().mean().item()
        plot_cargo_figure(
            env.occupancy.cpu().numpy(),
            trajectories,
            robots=env.robots,
            stage_line=env.stage_line,
            target=env.target,
            success_radius=env.success_radius,
            out=run_dir / "cargo.png",
            title=f"greedy stacked policy ({' -> '.join(env.robots)}), success {success:.1%}",
        )
    return {"robots": list(env.robots)}
