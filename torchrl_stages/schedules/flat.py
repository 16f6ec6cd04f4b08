"""The flat schedule: one learner over the whole task, no stages (the paper's end-to-end
baseline)."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from torchrl.record.loggers import Logger

from torchrl_stages.config import check
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.schedules.base import Probe, Schedule, StageStore, Trained, register_schedule
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


@register_schedule
class FlatSchedule(Schedule):
    """``schedule=flat`` (:func:`train_flat`): one learner, stage 0's file and checkpoints,
    acting in every stage (which must then share their observation and action entries)."""

    name = "flat"

    def train(self, task: StagedTask, store: StageStore | None = None, **kwargs) -> Trained:
        return Trained(*train_flat(task, store=store, **kwargs))

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
