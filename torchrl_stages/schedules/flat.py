"""The flat schedule: one learner over the whole task, no stages (the end-to-end baseline)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

from omegaconf import DictConfig

from torchrl_stages.config import check
from torchrl_stages.learners import Learner
from torchrl_stages.schedules.backward import run_stage
from torchrl_stages.schedules.base import Schedule, SeedGroup, Trained, register_schedule
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageDiscount


def flat_config(task: StagedTask) -> DictConfig:
    """The flat learner's config: stage 0's, with the stages' budgets summed."""
    cfg = task.stage_cfg(0).copy()
    cfg.frames = sum(int(task.stage_cfg(k).frames) for k in range(task.num_stages))
    return cfg


def train_flat(task: StagedTask, seeds: Sequence[int] = (0,), **kwargs) -> list[Trained]:
    """The flat schedule for every seed of ``seeds`` (``kwargs``: :class:`SeedGroup`'s).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16, gamma=0.9,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10, "num_stages": 2}
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": {"a": tiny, "b": tiny},
        ...                                     "env": env}))
        >>> [run] = train_flat(task)  # doctest: +SKIP
        >>> run.learners[0] is run.learners[1], run.results[0].frames  # doctest: +SKIP
        (True, 512)
    """
    return FlatSchedule().train(task, seeds, **kwargs)


@register_schedule
class FlatSchedule(Schedule):
    """``schedule=flat``: one learner acting in every stage, in stage 0's file and checkpoints;
    every transition is discounted with its stage's gamma (:class:`StageDiscount`)."""

    name = "flat"
    stacks_seeds = True

    def run(self, task: StagedTask, group: SeedGroup) -> list[Trained]:
        cfg = flat_config(task)
        num_envs = int(cfg.num_envs)
        episodes = None if task.start_states(None) is not None else int(cfg.eval_episodes)
        on_evaluate = None
        if group.probe is not None:

            def on_evaluate(learner: Learner, frames: int) -> None:
                group.probe([learner] * task.num_stages, frames)

        gammas = [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]
        train = functools.partial(
            run_stage,
            task,
            0,
            cfg,
            lambda copies: task.task_env(num_envs, start_stage=None, train=True, copies=copies),
            lambda copies: task.task_env(episodes, copies=copies),
            group,
            on_evaluate=on_evaluate,
            name="flat",
            gammas=gammas,
            postproc=StageDiscount(gammas, float(cfg.gamma)),
            extra_keys=["steps_to_next_obs"],
        )
        done = group.stage(0, train)
        return [Trained([learner] * task.num_stages, [result]) for learner, result in done]

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
