"""Backward schedule: train the last stage first, freeze it, hand its value to the one before."""

from __future__ import annotations

from collections.abc import Callable

import torch
from omegaconf import DictConfig
from torchrl.record.loggers import Logger

from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.stage import StageResult, StageTrainer
from torchrl_stages.task import StagedTask

StageCallback = Callable[[int, Learner, StageResult], None]


def train_backward(
    task: StagedTask,
    *,
    seed: int = 0,
    logger: Logger | None = None,
    progress: bool = False,
    on_stage_end: StageCallback | None = None,
) -> tuple[list[Learner], list[StageResult]]:
    """Trains stages N-1, ..., 0 of ``task`` in turn (the paper's backward schedule).

    Stage k's episodes start inside stage k; its transition reward uses the frozen value of the
    already trained stage k+1 (its target networks). ``on_stage_end`` runs as soon as a stage is
    done (the CLI writes the stage checkpoint there). Returns learners and results in stage order.
    """
    learners: list[Learner | None] = [None] * task.num_stages
    results: list[StageResult | None] = [None] * task.num_stages
    next_value = None
    for k in reversed(range(task.num_stages)):
        cfg: DictConfig = task.stage_cfg(k)
        torch.manual_seed(seed + k)
        env = task.stage_env(k, cfg.num_envs, next_value)
        env.set_seed(seed + k)
        eval_env = task.stage_eval_env(k, next_value)
        eval_env.set_seed(seed + 10_000 + k)
        learner = make_learner(cfg, task.specs(k))
        trainer = StageTrainer(
            k,
            learner,
            env,
            eval_env,
            cfg,
            logger=logger,
            progress=progress,
            name=task.stage_names[k],
        )
        results[k] = trainer.train()
        learners[k] = learner
        if on_stage_end is not None:
            on_stage_end(k, learner, results[k])
        next_value = learner.value()
    return learners, results
