"""The backward schedule: train the last stage first, freeze it, hand its value to the one
before."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import check
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.stacking import stack_learners
from torchrl_stages.loop import MetricsLog
from torchrl_stages.schedules.base import Probe, Schedule, StageStore, Trained, register_schedule
from torchrl_stages.seed_stage import (
    SeedsStageTrainer,
    finished_for_every_seed,
    seed_stacked_learner,
    start_stage_logs,
    train_and_keep,
)
from torchrl_stages.stage import StageResult, StageTrainer
from torchrl_stages.task import StagedTask


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
        >>> learners, results = train_backward(task)  # doctest: +SKIP
        >>> [r.frames for r in results]  # doctest: +SKIP
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


def seeded_stage_envs(
    task: StagedTask,
    stage: int,
    next_value: TensorDictModuleBase | None,
    seed: int,
    copies: int = 1,
) -> tuple[EnvBase, EnvBase]:
    """Stage ``stage``'s training and evaluation envs (``copies`` of each, one per seed of a
    stacked learner), seeded as a backward stage is: the global generator and the training
    env with ``seed + stage``, the evaluation env with ``seed + 10_000 + stage``."""
    torch.manual_seed(seed + stage)
    env = task.stage_env(stage, int(task.stage_cfg(stage).num_envs), next_value, copies=copies)
    env.set_seed(seed + stage)
    eval_env = task.stage_eval_env(stage, next_value, copies=copies)
    eval_env.set_seed(seed + 10_000 + stage)
    return env, eval_env


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
        >>> learner, result = train_stage(task, 0, seed=3)  # doctest: +SKIP
        >>> result.frames, result.stage  # doctest: +SKIP
        (128, 0)
    """
    cfg = task.stage_cfg(stage)
    env, eval_env = seeded_stage_envs(task, stage, next_value, seed)
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


def train_backward_seeds(
    task: StagedTask,
    seeds: Sequence[int],
    *,
    stores: Sequence[StageStore | None] | None = None,
    logs: Sequence[MetricsLog] | None = None,
    progress: bool = False,
    checkpoints: Callable[[int], StageCheckpoints] | None = None,
) -> list[Trained]:
    """Trains stages N-1, ..., 0 of ``task`` for every seed of ``seeds`` at once (the backward
    schedule, :class:`SeedsStageTrainer` per stage); returns each seed's learners and results
    in stage order (:class:`~torchrl_stages.seed_stage.SeedsStageTrainer` trains each stage).

    Seed ``s``'s stage ``k`` starts from the weights a single run with seed ``s`` starts it
    from (``torch.manual_seed(s + k)`` before its learner is built). ``stores`` (one per seed)
    skip the stages every seed has finished and keep each finished stage; ``logs`` (one per
    seed) receive each seed's metrics. ``checkpoints(k)`` gives the checkpoints of stage ``k``
    in progress, one state for all the seeds (a resumed stage goes on from the newest; without
    one, each store rewinds its seed's log to where the stage started); they are dropped once
    every seed's stage is kept.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> runs = train_backward_seeds(task, [0, 1])  # doctest: +SKIP
        >>> [[r.frames for r in run.results] for run in runs]  # doctest: +SKIP
        [[256, 256], [256, 256]]
    """
    n, num_stages = len(seeds), task.num_stages
    stores = list(stores) if stores is not None else [None] * n
    logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
    learners: list[list[Learner | None]] = [[None] * num_stages for _ in range(n)]
    results: list[list[StageResult | None]] = [[None] * num_stages for _ in range(n)]
    next_value = None
    resume = "stages-train seed=<s> resume=true hydra.run.dir=<its directory>"
    for k in reversed(range(num_stages)):
        cfg, specs = task.stage_cfg(k), task.specs(k)

        def plain(seeds: int | None = None, cfg=cfg, specs=specs) -> Learner:
            return make_learner(cfg, specs, device=task.device, seeds=seeds)

        if (done := finished_for_every_seed(stores, seeds, k, resume)) is not None:
            for i, (learner, result) in enumerate(done):
                learners[i][k], results[i][k] = learner, result
            next_value = stack_learners(plain(n), [d[0] for d in done]).value()
            continue
        joint = checkpoints(k) if checkpoints is not None else None
        start_stage_logs(stores, joint, k)
        # seeded_stage_envs seeds the generator with seed + k before a run builds stage k
        stacked = seed_stacked_learner(plain, seeds, offset=k)
        env, eval_env = seeded_stage_envs(task, k, next_value, seeds[0], copies=n)
        trainer = SeedsStageTrainer(
            k,
            stacked,
            env,
            eval_env,
            cfg,
            logs=logs,
            make_learner=plain,
            name=task.stage_names[k],
            progress=progress,
            seeds=seeds,
            checkpoints=joint,
        )
        for i, (learner, result) in enumerate(train_and_keep(trainer, stores)):
            learners[i][k], results[i][k] = learner, result
        next_value = stacked.value()
    return [Trained(learners[i], results[i]) for i in range(n)]


@register_schedule
class BackwardSchedule(Schedule):
    """``schedule=backward`` (:func:`train_backward`): stage k is trained from its own config
    and the frozen values of the stages after it, so a finished stage freezes itself and the
    stages after it; the env must start episodes inside a chosen stage."""

    name = "backward"
    reuses_stages = True
    stacks_seeds = True

    def train(self, task: StagedTask, store: StageStore | None = None, **kwargs) -> Trained:
        return Trained(*train_backward(task, store=store, **kwargs))

    def train_seeds(self, task: StagedTask, seeds: Sequence[int], **kwargs) -> list[Trained]:
        return train_backward_seeds(task, seeds, **kwargs)

    def frozen_stages(self, finished: set[int], num_stages: int) -> set[int]:
        return set(range(min(finished), num_stages)) if finished else set()

    def validate(self, cfg: DictConfig) -> None:
        check(
            bool(cfg.task.get("stage_starts", True)),
            "schedule",
            self.name,
            f"task '{cfg.task.name}' has stage_starts=false: its env cannot start inside a "
            "stage, which the backward schedule needs",
            "use schedule=joint (one phase from the task's own starts)",
        )
