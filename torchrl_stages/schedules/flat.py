"""The flat schedule: one learner over the whole task, no stages (the paper's end-to-end
baseline)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from omegaconf import DictConfig
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import check
from torchrl_stages.learners import Learner, make_learner
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
from torchrl_stages.transforms import StageDiscount


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
        >>> learners, results = train_flat(task)  # doctest: +SKIP
        >>> learners[0] is learners[1], results[0].frames  # doctest: +SKIP
        (True, 512)
    """
    done = store.finished(0) if store is not None else None
    if done is not None:
        return [done[0]] * task.num_stages, [done[1]]
    cfg = flat_config(task)
    env, eval_env = flat_envs(task, cfg, seed)
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
        on_evaluate=None if probe is None else lambda f: probe([learner] * task.num_stages, f),
        **stage_discounts(task, cfg),
    )
    result = trainer.train()
    if store is not None:
        store.save(0, learner, result)
    return [learner] * task.num_stages, [result]


def flat_envs(
    task: StagedTask, cfg: DictConfig, seed: int, copies: int = 1
) -> tuple[EnvBase, EnvBase]:
    """The flat learner's training env (the task's own starts) and evaluation env (every
    whole-task start, else ``eval_episodes``), ``copies`` of each (one per seed of a stacked
    learner), seeded as a flat run is: the global generator and the training env with
    ``seed``, the evaluation env with ``seed + 10_000``."""
    torch.manual_seed(seed)
    env = task.task_env(int(cfg.num_envs), start_stage=None, train=True, copies=copies)
    env.set_seed(seed)
    episodes = None if task.start_states(None) is not None else int(cfg.eval_episodes)
    eval_env = task.task_env(episodes, copies=copies)
    eval_env.set_seed(seed + 10_000)
    return env, eval_env


def stage_discounts(task: StagedTask, cfg: DictConfig) -> dict[str, Any]:
    """The stage trainer's arguments that discount each transition with its stage's gamma
    (:class:`~torchrl_stages.transforms.StageDiscount`), in training and in evaluations."""
    gammas = [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]
    return {
        "gammas": gammas,
        "postproc": StageDiscount(gammas, float(cfg.gamma)),
        "extra_keys": ["steps_to_next_obs"],
    }


def train_flat_seeds(
    task: StagedTask,
    seeds: Sequence[int],
    *,
    stores: Sequence[StageStore | None] | None = None,
    logs: Sequence[MetricsLog] | None = None,
    progress: bool = False,
    checkpoints: Callable[[int], StageCheckpoints] | None = None,
) -> list[Trained]:
    """:func:`train_flat` for every seed of ``seeds`` at once, their learners stacked
    (:class:`~torchrl_stages.seed_stage.SeedsStageTrainer`); ``stores``, ``logs`` and
    ``checkpoints`` as in :func:`~torchrl_stages.schedules.backward.train_backward_seeds`.
    Seed ``s`` starts from the weights of a flat run with seed ``s``."""
    n = len(seeds)
    stores = list(stores) if stores is not None else [None] * n
    logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
    resume = "stages-train schedule=flat seed=<s> resume=true hydra.run.dir=<its directory>"
    if (done := finished_for_every_seed(stores, seeds, 0, resume)) is not None:
        return [Trained([learner] * task.num_stages, [result]) for learner, result in done]
    cfg, specs = flat_config(task), task.specs(0)

    def plain(seeds: int | None = None) -> Learner:
        return make_learner(cfg, specs, device=task.device, seeds=seeds)

    joint = checkpoints(0) if checkpoints is not None else None
    start_stage_logs(stores, joint, 0)
    # flat_envs seeds the generator with the seed before a flat run builds its learner
    stacked = seed_stacked_learner(plain, seeds)
    env, eval_env = flat_envs(task, cfg, seeds[0], copies=n)
    trainer = SeedsStageTrainer(
        0,
        stacked,
        env,
        eval_env,
        cfg,
        logs=logs,
        make_learner=plain,
        name="flat",
        progress=progress,
        seeds=seeds,
        checkpoints=joint,
        **stage_discounts(task, cfg),
    )
    return [
        Trained([learner] * task.num_stages, [result])
        for learner, result in train_and_keep(trainer, stores)
    ]


@register_schedule
class FlatSchedule(Schedule):
    """``schedule=flat`` (:func:`train_flat`): one learner, stage 0's file and checkpoints,
    acting in every stage (which must then share their observation and action entries)."""

    name = "flat"
    stacks_seeds = True

    def train(self, task: StagedTask, store: StageStore | None = None, **kwargs) -> Trained:
        return Trained(*train_flat(task, store=store, **kwargs))

    def train_seeds(self, task: StagedTask, seeds: Sequence[int], **kwargs) -> list[Trained]:
        return train_flat_seeds(task, seeds, **kwargs)

    def checkpoint_scope(self, stage: int) -> int:
        return 0

    def stored_stage(self, stage: int) -> int:
        return 0

    def stage_name(self, task: StagedTask, stage: int) -> str:
        return "flat"

    def validate_task(self, cfg: DictConfig, task: StagedTask) -> None:
        first = task.specs(0)
        for k, name in enumerate(cfg.task.stages):
            specs = task.specs(k)
            check(
                specs.action_key == first.action_key
                and list(specs.observation_keys) == list(first.observation_keys),
                "schedule",
                self.name,
                f"one learner acts in every stage, but stage {k} ({name}) reads "
                f"{list(specs.observation_keys)} and writes {specs.action_key!r} where stage 0 "
                f"reads {list(first.observation_keys)} and writes {first.action_key!r}",
                "give the stages one action entry (e.g. cargo's single-robot task: "
                "task.env.robots=[propelled] ~task.stages.slider), or use schedule=backward",
            )
