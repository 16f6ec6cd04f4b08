"""Backward schedule: train the last stage first, freeze it, hand its value to the one before."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Protocol

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.stage import StageResult, StageTrainer
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageDiscount


class StageStore(Protocol):
    """Where a schedule keeps its stages (a run directory, see
    :class:`~torchrl_stages.experiment.Experiment`): finished ones, checkpoints of the one in
    progress."""

    def finished(self, stage: int) -> tuple[Learner, StageResult] | None:
        """The stage if it was already trained (a resumed run), else ``None``."""

    def begin(self, stage: int) -> StageCheckpoints | None:
        """The checkpoints the stage's loop saves to and resumes from."""

    def save(self, stage: int, learner: Learner, result: StageResult) -> None:
        """Keeps a stage that just finished."""


#: ``probe(learners, frames)``: follows the whole task during training (see ``eval.probe``);
#: called at every evaluation of the stage that holds the whole-task starts, with the
#: learners as they are and the frames collected so far over all stages
Probe = Callable[[list[Learner], int], None]


def train_backward(
    task: StagedTask,
    *,
    seed: int = 0,
    logger: Logger | None = None,
    progress: bool = False,
    store: StageStore | None = None,
    probe: Probe | None = None,
    compile: str = "off",
) -> tuple[list[Learner], list[StageResult]]:
    """Trains stages N-1, ..., 0 of ``task`` in turn (the paper's backward schedule).

    Stage k's episodes start inside stage k; its transition reward uses the frozen value of the
    already trained stage k+1 (its target networks). Each stage is :func:`train_stage`, seeded
    from ``seed`` and its index alone, so a stage's training does not depend on how the ones
    after it were reached (trained now, or loaded by a resumed run). ``store`` (optional)
    skips stages that are already trained, checkpoints the one in progress and keeps each
    finished stage. Returns learners and results in stage order.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> from torchrl_stages.task import StagedTask
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},  # stages 0 and 1
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> learners, results = train_backward(task)
        >>> [r.frames for r in results]
        [256, 256]
    """
    learners: list[Learner | None] = [None] * task.num_stages
    results: list[StageResult | None] = [None] * task.num_stages
    next_value, frames_before = None, 0
    for k in reversed(range(task.num_stages)):
        done = store.finished(k) if store is not None else None
        if done is not None:
            learners[k], results[k] = done
        else:
            on_evaluate = None
            if probe is not None and k == 0:

                def on_evaluate(learner: Learner, frames: int, before=frames_before) -> None:
                    probe([learner, *learners[1:]], before + frames)

            learners[k], results[k] = train_stage(
                task,
                k,
                next_value,
                seed=seed,
                logger=logger,
                progress=progress,
                checkpoints=store.begin(k) if store is not None else None,
                on_evaluate=on_evaluate,
                compile=compile,
            )
            if store is not None:
                store.save(k, learners[k], results[k])
        next_value = learners[k].value()
        frames_before += results[k].frames
    return learners, results


def train_stage(
    task: StagedTask,
    stage: int,
    next_value: TensorDictModuleBase | None = None,
    *,
    seed: int = 0,
    logger: Logger | None = None,
    progress: bool = False,
    checkpoints: StageCheckpoints | None = None,
    on_evaluate: Callable[[Learner, int], None] | None = None,
    compile: str = "off",
) -> tuple[Learner, StageResult]:
    """Trains stage ``stage`` of ``task`` on its own, as the backward schedule does.

    ``next_value`` is the frozen value of stage ``stage + 1`` (``None`` for the last stage).
    The global generator and the training env are seeded with ``seed + stage``, the evaluation
    env with ``seed + 10_000 + stage``: with the same ``next_value``, the stage is the one a
    whole backward run with ``seed`` trains (what ``scripts/benchmark_stage.py`` relies on).
    ``on_evaluate(learner, frames)`` runs after each of the stage's evaluations. A missing or
    superfluous ``next_value`` fails in :class:`~torchrl_stages.transforms.StageTransform`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> from torchrl_stages.task import StagedTask
        >>> cfg = DQNConfig(frames=128, frames_per_batch=64, num_envs=8, batch_size=16)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 5, "num_stages": 1}
        >>> task = StagedTask(OmegaConf.create({"name": "g", "stages": {"a": cfg}, "env": env}))
        >>> learner, result = train_stage(task, 0, seed=3)  # the last (and only) stage
        >>> result.frames, result.stage
        (128, 0)
    """
    cfg = task.stage_cfg(stage)
    torch.manual_seed(seed + stage)
    env = task.stage_env(stage, cfg.num_envs, next_value)
    env.set_seed(seed + stage)
    eval_env = task.stage_eval_env(stage, next_value)
    eval_env.set_seed(seed + 10_000 + stage)
    learner = make_learner(cfg, task.specs(stage), compile, task.device)
    trainer = StageTrainer(
        stage,
        learner,
        env,
        eval_env,
        cfg,
        logger=logger,
        progress=progress,
        name=task.stage_names[stage],
        checkpoints=checkpoints,
        on_evaluate=None if on_evaluate is None else functools.partial(on_evaluate, learner),
    )
    return learner, trainer.train()


def flat_config(task: StagedTask) -> DictConfig:
    """The flat learner's config: stage 0's, with the stages' budgets summed."""
    cfg = task.stage_cfg(0).copy()
    cfg.frames = sum(int(task.stage_cfg(k).frames) for k in range(task.num_stages))
    return cfg


def train_flat(
    task: StagedTask,
    *,
    seed: int = 0,
    logger: Logger | None = None,
    progress: bool = False,
    store: StageStore | None = None,
    probe: Probe | None = None,
    compile: str = "off",
) -> tuple[list[Learner], list[StageResult]]:
    """One learner over the whole task, no stages (the paper's end-to-end baseline).

    It has stage 0's algorithm and hyper-parameters and the sum of the stages' budgets, starts
    from the task's own starts, and discounts every transition with the gamma of its stage
    (:class:`~torchrl_stages.transforms.StageDiscount`), so it optimizes the objective the
    stacked learners do. Its evaluations are whole-task episodes. Returns the learner once per
    stage (it acts everywhere) and its one result.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> from torchrl_stages.task import StagedTask
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16, gamma=0.9,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> learners, results = train_flat(task)
        >>> learners[0] is learners[1], results[0].frames
        (True, 512)
    """
    done = store.finished(0) if store is not None else None
    if done is not None:
        return [done[0]] * task.num_stages, [done[1]]
    cfg = flat_config(task)
    gammas = [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]
    torch.manual_seed(seed)
    env = task.task_env(int(cfg.num_envs), start_stage=None, train=True)
    env.set_seed(seed)
    eval_env = task.task_env(None if task.start_states(None) is not None else cfg.eval_episodes)
    eval_env.set_seed(seed + 10_000)
    learner = make_learner(cfg, task.specs(0), compile, task.device)
    trainer = StageTrainer(
        0,
        learner,
        env,
        eval_env,
        cfg,
        logger=logger,
        progress=progress,
        name="flat",
        checkpoints=store.begin(0) if store is not None else None,
        gammas=gammas,
        postproc=StageDiscount(gammas, float(cfg.gamma)),
        extra_keys=["steps_to_next_obs"],
        on_evaluate=None if probe is None else lambda f: probe([learner] * task.num_stages, f),
    )
    result = trainer.train()
    if store is not None:
        store.save(0, learner, result)
    return [learner] * task.num_stages, [result]
