"""The flat schedule: one learner over the whole task, no stages (the end-to-end baseline)."""

from __future__ import annotations

from collections.abc import Sequence

from omegaconf import DictConfig
from torchrl.envs import EnvBase

from torchrl_stages.config import check
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.schedules.base import Schedule, SeedGroup, Trained, register_schedule
from torchrl_stages.seeding import EVAL_OFFSET, seeded, stage_seed
from torchrl_stages.stage import StageTrainer
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
        >>> from torchrl_stages.task import StagedTask
        >>> tiny = DQNConfig(frames=256, frames_per_batch=128, num_envs=16, gamma=0.9,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> [run] = train_flat(task)  # doctest: +SKIP
        >>> run.learners[0] is run.learners[1], run.results[0].frames  # doctest: +SKIP
        (True, 512)
    """
    return FlatSchedule().train(task, seeds, **kwargs)


def flat_envs(
    task: StagedTask, cfg: DictConfig, seed: int, copies: int = 1
) -> tuple[EnvBase, EnvBase]:
    """The training env (the task's own starts) and evaluation env (every whole-task start, else
    ``eval_episodes``), ``copies`` of each, seeded as stage 0's."""
    env = task.task_env(int(cfg.num_envs), start_stage=None, train=True, copies=copies)
    env.set_seed(stage_seed(seed, 0))
    episodes = None if task.start_states(None) is not None else int(cfg.eval_episodes)
    eval_env = task.task_env(episodes, copies=copies)
    eval_env.set_seed(stage_seed(seed, 0) + EVAL_OFFSET)
    return env, eval_env


@register_schedule
class FlatSchedule(Schedule):
    """``schedule=flat``: one learner acting in every stage, in stage 0's file and checkpoints;
    every transition is discounted with its stage's gamma (:class:`StageDiscount`)."""

    name = "flat"
    stacks_seeds = True

    def run(self, task: StagedTask, group: SeedGroup) -> list[Trained]:
        done = group.finished(0)
        if done is None:
            seeds, cfg, specs = group.seeds, flat_config(task), task.specs(0)

            def make(seeds: int | None = None) -> Learner:
                return make_learner(cfg, specs, group.compile, task.device, seeds=seeds)

            learner, (env, eval_env) = seeded(
                make, seeds, 0, lambda: flat_envs(task, cfg, seeds[0], copies=len(seeds))
            )
            on_evaluate = None
            if group.probe is not None:

                def on_evaluate(frames: int) -> None:
                    group.probe([learner] * task.num_stages, frames)

            gammas = [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]
            checkpoints = group.begin(0)
            trainer = StageTrainer(
                0,
                learner,
                env,
                eval_env,
                cfg,
                logs=group.logs,
                make_learner=make,
                name="flat",
                progress=group.progress,
                seeds=seeds,
                checkpoints=checkpoints,
                on_evaluate=on_evaluate,
                gammas=gammas,
                postproc=StageDiscount(gammas, float(cfg.gamma)),
                extra_keys=["steps_to_next_obs"],
            )
            done = group.keep(0, trainer.train(), checkpoints)
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
