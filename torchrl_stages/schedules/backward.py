"""The backward schedule: train the last stage first, freeze it, hand its value to the one
before."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import check
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.stacking import stack_learners
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.schedules.base import (
    Probe,
    Schedule,
    StageKeeper,
    Trained,
    begin_loop,
    finished_for_every_seed,
    register_schedule,
)
from torchrl_stages.seeding import EVAL_OFFSET, seeded, stage_seed
from torchrl_stages.stage import StageResult, StageTrainer
from torchrl_stages.task import StagedTask


def train_backward(
    task: StagedTask,
    seeds: Sequence[int] = (0,),
    *,
    keepers: Sequence[StageKeeper | None] | None = None,
    logs: Sequence[MetricsLog] | None = None,
    checkpoints: Callable[[int | str], StageCheckpoints] | None = None,
    progress: bool = False,
    probe: Probe | None = None,
    compile: str = "off",
) -> list[Trained]:
    """Trains stages N-1, ..., 0 of ``task`` in turn (the paper's backward schedule), for
    every seed of ``seeds`` at once; returns each seed's learners and results in stage order.

    Stage k's episodes start inside stage k; its transition reward uses the frozen value of the
    already trained stage k+1 (its target networks). Each stage is :func:`train_stage`, seeded
    from the seed and its index alone (:mod:`~torchrl_stages.seeding`), so a stage's training
    does not depend on how the ones after it were reached (trained now, or loaded by a resumed
    run). ``keepers`` (one per seed) skip the stages every seed has finished and keep each
    finished stage; ``logs`` (one per seed) receive each seed's metrics; ``checkpoints(k)``
    gives the checkpoints of stage ``k`` in progress, one state for all the seeds, dropped once
    every seed's stage is kept. ``probe`` (one seed) follows the whole task at stage 0's
    evaluations.

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
        >>> runs = train_backward(task, [0, 1])  # doctest: +SKIP
        >>> [[r.frames for r in run.results] for run in runs]  # doctest: +SKIP
        [[256, 256], [256, 256]]
    """
    n, num_stages = len(seeds), task.num_stages
    keepers = list(keepers) if keepers is not None else [None] * n
    logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
    learners: list[list[Learner]] = [[None] * num_stages for _ in range(n)]  # type: ignore[list-item]
    results: list[list[StageResult]] = [[None] * num_stages for _ in range(n)]  # type: ignore[list-item]
    next_value, frames_before = None, 0
    resume = "stages-train seed=<s> resume=true hydra.run.dir=<its directory>"
    for k in reversed(range(num_stages)):
        done = finished_for_every_seed(keepers, seeds, k, resume)
        if done is None:
            on_evaluate = None
            if probe is not None and k == 0:

                def on_evaluate(learner: Learner, frames: int, before=frames_before) -> None:
                    probe([learner, *learners[0][1:]], before + frames)

            done = train_stage(
                task,
                k,
                next_value,
                seeds=seeds,
                logs=logs,
                progress=progress,
                checkpoints=begin_loop(keepers, checkpoints, k),
                on_evaluate=on_evaluate,
                compile=compile,
                keep=keepers,
            )
        for i, (learner, result) in enumerate(done):
            learners[i][k], results[i][k] = learner, result
        next_value = stage_value(task, k, [learner for learner, _ in done])
        frames_before += results[0][k].frames
    return [Trained(learners[i], results[i]) for i in range(n)]


def stage_value(task: StagedTask, stage: int, learners: Sequence[Learner]) -> TensorDictModuleBase:
    """The frozen value of ``stage`` that the stage before it learns against: one seed's
    learner's, or, for several, that of their seed-stacked learner."""
    if len(learners) == 1:
        return learners[0].value()
    cfg, specs = task.stage_cfg(stage), task.specs(stage)
    stacked = make_learner(cfg, specs, device=task.device, seeds=len(learners))
    return stack_learners(stacked, learners).value()


def train_stage(
    task: StagedTask,
    stage: int,
    next_value: TensorDictModuleBase | None = None,
    *,
    seeds: Sequence[int] = (0,),
    logs: Sequence[MetricsLog] | None = None,
    progress: bool = False,
    checkpoints: StageCheckpoints | None = None,
    on_evaluate: Callable[[Learner, int], None] | None = None,
    compile: str = "off",
    keep: Sequence[StageKeeper | None] | None = None,
) -> list[tuple[Learner, StageResult]]:
    """Trains stage ``stage`` of ``task`` on its own, as the backward schedule does, for every
    seed of ``seeds`` at once; returns each seed's learner and result.

    ``next_value`` is the frozen value of stage ``stage + 1`` (``None`` for the last stage;
    several seeds: their stacked value). The learner and envs are seeded by the rule of
    :mod:`~torchrl_stages.seeding`: with the same ``next_value``, the stage is the one a whole
    backward run with the seed trains (what ``scripts/benchmark_stage.py`` relies on).
    ``on_evaluate(learner, frames)`` runs after each of the stage's evaluations (one seed).
    ``keep`` (one keeper per seed) keeps each seed's finished stage, then the stage's
    ``checkpoints`` go. A missing or superfluous ``next_value`` fails in
    :class:`~torchrl_stages.transforms.StageTransform`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> from torchrl_stages.task import StagedTask
        >>> cfg = DQNConfig(frames=128, frames_per_batch=64, num_envs=8, batch_size=16)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 5, "num_stages": 1}
        >>> task = StagedTask(OmegaConf.create({"name": "g", "stages": {"a": cfg}, "env": env}))
        >>> [(r.frames, r.stage) for _, r in train_stage(task, 0, seeds=[3])]  # doctest: +SKIP
        [(128, 0)]
    """
    cfg, specs, n = task.stage_cfg(stage), task.specs(stage), len(seeds)

    def make(seeds: int | None = None) -> Learner:
        return make_learner(cfg, specs, compile, task.device, seeds=seeds)

    def envs() -> tuple[EnvBase, EnvBase]:
        env = task.stage_env(stage, int(cfg.num_envs), next_value, copies=n)
        env.set_seed(stage_seed(seeds[0], stage))
        eval_env = task.stage_eval_env(stage, next_value, copies=n)
        eval_env.set_seed(stage_seed(seeds[0], stage) + EVAL_OFFSET)
        return env, eval_env

    learner, (env, eval_env) = seeded(make, seeds, stage_seed(0, stage), envs)
    trainer = StageTrainer(
        stage,
        learner,
        env,
        eval_env,
        cfg,
        logs=logs,
        make_learner=make,
        name=task.stage_names[stage],
        progress=progress,
        seeds=seeds,
        checkpoints=checkpoints,
        on_evaluate=None if on_evaluate is None else functools.partial(on_evaluate, learner),
    )
    return keep_stage(trainer, keep)


def keep_stage(
    trainer: StageTrainer, keepers: Sequence[StageKeeper | None] | None
) -> list[tuple[Learner, StageResult]]:
    """Trains ``trainer``'s stage; each seed's learner and result is kept in its keeper
    (``keeper.save``; a ``None`` keeper keeps nothing), then the stage's checkpoints, which the
    kept stage supersedes, are dropped. Returns each seed's learner and result."""
    out = trainer.train()
    for keeper, (learner, result) in zip(keepers or [None] * len(out), out, strict=True):
        if keeper is not None:
            keeper.save(trainer.stage, learner, result)
    if trainer.checkpoints is not None:
        trainer.checkpoints.clear()
    return out


@register_schedule
class BackwardSchedule(Schedule):
    """``schedule=backward`` (:func:`train_backward`): stage k is trained from its own config
    and the frozen values of the stages after it, so a finished stage freezes itself and the
    stages after it; the env must start episodes inside a chosen stage."""

    name = "backward"
    reuses_stages = True
    stacks_seeds = True

    def train(self, task: StagedTask, seeds: Sequence[int] = (0,), **kwargs) -> list[Trained]:
        return train_backward(task, seeds, **kwargs)

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
