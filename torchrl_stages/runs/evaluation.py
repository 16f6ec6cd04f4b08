"""A run's whole-task evaluation (``eval.json``), its probe during training, and the lines a
finished run prints."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from torchrl_stages.evaluate import evaluate_task
from torchrl_stages.handoff import handoff_diagnostics, plot_handoffs
from torchrl_stages.integrity import atomic_write
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runs.layout import EVAL_FILE, METRICS_FILE
from torchrl_stages.seeding import TASK_EVAL_OFFSET
from torchrl_stages.task import StagedTask
from torchrl_stages.task_registry import task_report


@torch.no_grad()
def probe_task(task: StagedTask, learners: Sequence[Learner], seed: int) -> dict[str, float]:
    """Whole-task success rate of the current learners, plus the task's own probe metrics."""
    policy = StackedPolicy([learner.policy for learner in learners])
    episodes = int(task.stage_cfg(0).eval_episodes)
    stats = evaluate_task(task, policy, episodes, seed).stats.summary()
    out = {"success_rate": stats["success_rate"]}
    extra = task_report(task.name)
    if extra is not None and extra.probe is not None:
        out.update(extra.probe(task, learners))
    return out


def evaluate_run(
    cfg: DictConfig, task: StagedTask, learners: Sequence[Learner], run_dir: Path, training: dict
) -> dict[str, Any]:
    """Evaluates the greedy stacked policy on whole-task episodes; writes ``eval.json``."""
    policy = StackedPolicy([learner.policy for learner in learners])
    seed = int(cfg.seed) + TASK_EVAL_OFFSET
    evaluation = evaluate_task(task, policy, int(cfg.eval.episodes), seed, interruptible=True)
    result: dict[str, Any] = {"task": cfg.task.name, **evaluation.summary(), "training": training}
    report = task_report(str(cfg.task.name))
    if report is not None and report.report is not None:
        result["task_metrics"] = report.report(
            task, learners, evaluation, run_dir, plots=cfg.eval.plots
        )
        result["headline_metrics"] = list(report.headline)
    if evaluation.handoffs:  # how each stage's value holds where the stage before hands over
        records = handoff_diagnostics(task, learners, evaluation.handoffs, seed)
        if cfg.eval.plots:
            plot_handoffs(records, run_dir / "handoff.png")
        keep = ("values", "returns")
        result["handoff"] = [{k: v for k, v in r.items() if k not in keep} for r in records]
    if cfg.eval.plots and (run_dir / METRICS_FILE).is_file():
        from torchrl_stages.plots import plot_learning_curves

        plot_learning_curves(run_dir / METRICS_FILE, run_dir / "learning_curves.png")
    result = json.loads(json.dumps(result), parse_constant=lambda _: None)  # NaN, inf: null
    atomic_write(run_dir / EVAL_FILE, lambda tmp: tmp.write_text(json.dumps(result, indent=2)))
    return result


STARTS = {"all": "every whole-task start", "fixed": "one fixed start", "random": "random starts"}


def format_summary(result: dict[str, Any], run_dir: Path) -> str:
    """The lines printed at the end of a run: its ``eval.json`` summary, then its files."""
    starts = STARTS.get(str(result.get("starts")), "random starts")
    lines = [
        f"task {result['task']}: success {result['success_rate']:.1%} over "
        f"{result['episodes']} whole-task episodes ({starts}), mean return "
        f"{result['mean_return']:.3f}, mean steps {result['mean_steps']:.1f}"
    ]
    metrics = result.get("task_metrics", {}).items()
    lines += [f"  {key}: {value}" for key, value in metrics if key != "path_from_origin"]
    lines += [f"Run directory: {run_dir}", f"  {EVAL_FILE}: {Path(run_dir) / EVAL_FILE}"]
    lines += [f"  figure: {path}" for path in sorted(Path(run_dir).glob("*.png"))]
    return "\n".join(lines)
