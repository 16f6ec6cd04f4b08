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
from torchrl_stages.schedules.base import Schedule, SeedGroup, Trained, register_schedule
from torchrl_stages.seeding import EVAL_OFFSET, seeded, stage_seed
from torchrl_stages.stage import SeedResults, StageTrainer
from torchrl_stages.task import StagedTask


def train_backward(task: StagedTask, seeds: Sequence[int] = (0,), **kwargs) -> list[Trained]:
    """The backward schedule for every seed of ``seeds`` (``kwargs``: :class:`SeedGroup`'s).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10, "num_stages": 2}
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": {"a": tiny, "b": tiny},
        ...                                     "env": env}))
        >>> runs = train_backward(task, [0, 1])  # doctest: +SKIP
        >>> [[r.frames for r in run.results] for run in runs]  # doctest: +SKIP
        [[256, 256], [256, 256]]
    """
    return BackwardSchedule().train(task, seeds, **kwargs)


def stage_value(task: StagedTask, stage: int, learners: Sequence[Learner]) -> TensorDictModuleBase:
    """The frozen value of ``stage`` (several seeds: of their seed-stacked learner, the one
    they were trained in where each is its row)."""
    if len(learners) == 1:
        return learners[0].value()
    rows = [learner.stacked_row for learner in learners]
    stacked = rows[0][0] if rows[0] is not None else None
    if stacked is None or rows != [(stacked, i) for i in range(len(learners))]:
        cfg, specs = task.stage_cfg(stage), task.specs(stage)
        stacked = make_learner(cfg, specs, device=task.device, seeds=len(learners))
        stack_learners(stacked, learners)
    return stacked.value()


def run_stage(
    task: StagedTask,
    stage: int,
    cfg: DictConfig,
    train_env: Callable[[int], EnvBase],
    eval_env: Callable[[int], EnvBase],
    group: SeedGroup,
    **kwargs,
) -> SeedResults:
    """Trains a learner of ``cfg`` as stage ``stage`` for every seed of ``group``, its envs
    (``train_env(copies)``, ``eval_env(copies)``) seeded by the seeding rule; ``kwargs``:
    :class:`StageTrainer`'s."""
    seeds = group.seeds
    make = functools.partial(make_learner, cfg, task.specs(stage), group.compile, task.device)

    def envs() -> tuple[EnvBase, EnvBase]:
        env = train_env(len(seeds))
        env.set_seed(stage_seed(seeds[0], stage))
        evaluation = eval_env(len(seeds))
        evaluation.set_seed(stage_seed(seeds[0], stage) + EVAL_OFFSET)
        return env, evaluation

    learner, (env, evaluation) = seeded(make, seeds, stage_seed(0, stage), envs)
    return StageTrainer(
        stage,
        learner,
        env,
        evaluation,
        cfg,
        logs=group.logs,
        make_learner=make,
        progress=group.progress,
        seeds=seeds,
        **kwargs,
    ).train()


def train_stage(
    task: StagedTask,
    stage: int,
    next_value: TensorDictModuleBase | None = None,
    *,
    seeds: Sequence[int] = (0,),
    checkpoints: StageCheckpoints | None = None,
    on_evaluate: Callable[[Learner, int], None] | None = None,
    group: SeedGroup | None = None,
    **kwargs,
) -> SeedResults:
    """Trains stage ``stage`` against ``next_value`` (stage ``stage + 1``'s frozen value) for
    every seed of ``seeds`` (or of ``group``; ``kwargs``: :class:`SeedGroup`'s), as a backward run
    does; each seed's learner and result. A stage is seeded from the seed and its index alone.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> cfg = DQNConfig(frames=128, frames_per_batch=64, num_envs=8, batch_size=16)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 5, "num_stages": 1}
        >>> task = StagedTask(OmegaConf.create({"name": "g", "stages": {"a": cfg}, "env": env}))
        >>> [(r.frames, r.stage) for _, r in train_stage(task, 0, seeds=[3])]  # doctest: +SKIP
        [(128, 0)]
    """
    cfg = task.stage_cfg(stage)
    return run_stage(
        task,
        stage,
        cfg,
        lambda copies: task.stage_env(stage, int(cfg.num_envs), next_value, copies=copies),
        lambda copies: task.stage_eval_env(stage, next_value, copies=copies),
        group or SeedGroup(list(seeds), **kwargs),
        on_evaluate=on_evaluate,
        name=task.stage_names[stage],
        checkpoints=checkpoints,
    )


@register_schedule
class BackwardSchedule(Schedule):
    """``schedule=backward``: stages N-1, ..., 0 in turn, each against the frozen value of the
    one after it; a finished stage freezes itself and the stages after it."""

    name = "backward"
    reuses_stages = True
    stacks_seeds = True

    def run(self, task: StagedTask, group: SeedGroup) -> list[Trained]:
        num_stages = task.num_stages
        done: list[SeedResults] = [[] for _ in range(num_stages)]
        next_value, frames_before = None, 0
        for k in reversed(range(num_stages)):
            on_evaluate = None
            if group.probe is not None and k == 0:

                def on_evaluate(learner: Learner, frames: int, before=frames_before) -> None:
                    group.probe([learner, *(stage[0][0] for stage in done[1:])], before + frames)

            train = functools.partial(
                train_stage, task, k, next_value, on_evaluate=on_evaluate, group=group
            )
            done[k] = group.stage(k, train)
            next_value = stage_value(task, k, [learner for learner, _ in done[k]])
            frames_before += done[k][0][1].frames
        return Trained.per_seed(done)

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
