"""Whole-task evaluation of a trained run: ``eval.json``, figures, printed summary."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask
from torchrl_stages.tasks import REPORTS

EVAL_FILE = "eval.json"


def evaluate_run(
    cfg: DictConfig,
    task: StagedTask,
    learners: Sequence[Learner],
    run_dir: Path,
    training: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Evaluates the greedy stacked policy on whole-task episodes; writes ``eval.json``.

    ``cfg.eval.episodes`` episodes start from the task's whole-task start distribution; the
    task's report (if any) adds its own metrics and figures; ``training`` (wall-clock, frames,
    updates per stage) is stored alongside.
    """
    policy = StackedPolicy([learner.policy for learner in learners])
    env = task.task_env(cfg.eval.episodes)
    env.set_seed(cfg.seed + 20_000)
    stats, rollout = evaluate_policy(env, policy, int(getattr(env.base_env, "max_steps", 1000)))
    stage_steps = rollout["stage"].squeeze(-1)  # [B, T]: steps spent in each stage
    in_first = rollout["next", "done"].squeeze(-1).cumsum(-1).roll(1, -1)
    in_first[..., 0] = 0
    steps_per_stage = [
        ((stage_steps == k) & (in_first == 0)).sum(-1).float().mean().item()
        for k in range(task.num_stages)
    ]
    result: dict[str, Any] = {
        "task": cfg.task.name,
        "episodes": int(cfg.eval.episodes),
        **stats.summary(),
        "mean_steps_per_stage": steps_per_stage,
        "training": training or {},
    }
    report = REPORTS.get(cfg.task.name)
    if report is not None:
        result["task_metrics"] = report(task, learners, run_dir, plots=cfg.eval.plots)
    if cfg.eval.plots and (run_dir / "metrics.csv").is_file():
        from torchrl_stages.plots import plot_learning_curves

        plot_learning_curves(run_dir / "metrics.csv", run_dir / "learning_curves.png")
    (run_dir / EVAL_FILE).write_text(json.dumps(result, indent=2))
    return result


def format_summary(result: dict[str, Any], run_dir: Path) -> str:
    """A few human-readable lines for the end of a run."""
    lines = [
        f"task {result['task']}: success {result['success_rate']:.1%} over {result['episodes']} "
        f"whole-task episodes, mean return {result['mean_return']:.3f}, "
        f"mean steps {result['mean_steps']:.1f}",
    ]
    extra = result.get("task_metrics", {})
    for key, value in extra.items():
        if key != "path_from_origin":
            lines.append(f"  {key}: {value}")
    lines.append(f"Run directory: {run_dir}")
    return "\n".join(lines)
