"""A run directory on disk: config, per-stage checkpoints, and loading them back."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

CONFIG_FILE = "config.yaml"


def stage_file(run_dir: str | Path, stage: int) -> Path:
    return Path(run_dir) / f"stage_{stage}.pt"


def save_config(cfg: DictConfig, run_dir: Path) -> None:
    """Writes the resolved config; :func:`load_run` rebuilds everything from it."""
    OmegaConf.save(cfg, Path(run_dir) / CONFIG_FILE, resolve=True)


def save_stage(run_dir: Path, stage: int, name: str, learner: Learner, result: StageResult) -> Path:
    """Writes ``stage_<k>.pt``: weights (targets included), optimizers, exploration, counters."""
    learner.check_finite()  # never write a non-finite checkpoint
    path = stage_file(run_dir, stage)
    state = {"stage": stage, "name": name, "algo": learner.algo, "result": asdict(result)}
    torch.save({**state, **learner.checkpoint()}, path)
    return path


@dataclass
class LoadedRun:
    """A finished run read back from disk (learners and results in stage order)."""

    cfg: DictConfig
    task: StagedTask
    learners: list[Learner]
    results: list[dict[str, Any]]


def load_run(run_dir: str | Path, device: str | torch.device = "cpu") -> LoadedRun:
    """Config, task, trained learners and training results of a finished run directory."""
    run_dir = Path(run_dir)
    config = run_dir / CONFIG_FILE
    if not config.is_file():
        raise FileNotFoundError(
            f"{config} not found: {run_dir} is not a torchrl-stages run directory "
            "(pass the directory that `stages-train` printed at the end)."
        )
    cfg = OmegaConf.load(config)
    task = StagedTask(cfg.task, device=device)
    missing = [
        stage_file(run_dir, k).name
        for k in range(task.num_stages)
        if not stage_file(run_dir, k).is_file()
    ]
    if missing:
        raise FileNotFoundError(
            f"{run_dir} lacks {', '.join(missing)}: those stages never finished training. "
            "Train the run to the end (stages are written from the last one backwards)."
        )
    learners, results = [], []
    for k in range(task.num_stages):
        learner = make_learner(task.stage_cfg(k), task.specs(k)).to(device)
        state = torch.load(stage_file(run_dir, k), map_location=device)
        learner.load_checkpoint(state)
        learners.append(learner)
        results.append(state["result"])
    return LoadedRun(cfg, task, learners, results)


def load_policy(run_dir: str | Path, device: str | torch.device = "cpu") -> StackedPolicy:
    """The greedy stacked policy of a finished run.

    Examples:
        >>> from torchrl_stages import load_policy  # doctest: +SKIP
        >>> policy = load_policy("outputs/2026-11-21/16-00-00")  # doctest: +SKIP
        >>> env.rollout(200, policy)  # an env tagged by StageTransform  # doctest: +SKIP
    """
    run = load_run(run_dir, device)
    return StackedPolicy([learner.policy for learner in run.learners])
