"""A multi-stage task built from its config: envs for each stage, specs for each learner."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Compose, EnvBase, RewardSum, TransformedEnv

from torchrl_stages.learners import StageSpecs
from torchrl_stages.transforms import SUCCESS_KEY, StageTransform


def tile_starts(starts: dict[str, Any], copies: int) -> dict[str, Any]:
    """:meth:`StagedTask.start_states` arguments for ``copies`` consecutive copies of the batch."""
    if copies == 1:
        return starts
    (size,) = tuple(starts["batch_size"])
    out = dict(starts, batch_size=(size * copies,))
    for key, value in starts.items():
        if isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == size:
            out[key] = value.repeat(copies, *[1] * (value.ndim - 1))
    return out


class StagedTask:
    """Makes the envs of a task config (``cfg.task``) for training and evaluation; ``copies``
    arguments hold one copy of a batch per seed of a seed-stacked learner.

    Examples:
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10, "num_stages": 2}
        >>> stages = {"a": {"gamma": 0.9}, "b": {"gamma": 0.9}}
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": stages, "env": env}))
        >>> task.stage_env(1, batch_size=4).rollout(2, break_when_any_done=False)["stage"].shape
        torch.Size([4, 2, 1])
    """

    def __init__(self, cfg: DictConfig, device: str | torch.device = "cpu") -> None:
        self.cfg, self.device, self.name = cfg, torch.device(device), str(cfg.name)
        self.stage_names: list[str] = list(cfg.stages.keys())
        self.stage_starts = bool(cfg.get("stage_starts", True))  # episodes may start in stage k
        self.spec_env = self.base_env(batch_size=1)  # the env the learners' specs are read from
        self.num_stages = int(self.spec_env.num_stages)

    @staticmethod
    def env_num_stages(cfg: DictConfig) -> int:
        """The ``num_stages`` of the env that the task config ``cfg`` builds (then closed)."""
        task = StagedTask(cfg)
        task.spec_env.close()
        return task.num_stages

    def stage_cfg(self, stage: int) -> DictConfig:
        return self.cfg.stages[self.stage_names[stage]]

    def base_env(
        self, batch_size: int | Sequence[int], start_stage: int | None = None, **overrides: Any
    ) -> EnvBase:
        """The task's env without stage transform (``overrides`` go to its constructor)."""
        batch = (int(batch_size),) if isinstance(batch_size, int) else tuple(batch_size)
        kwargs = {**OmegaConf.to_container(self.cfg.env, resolve=True), **overrides}
        if self.stage_starts:  # an env without stage starts takes no start_stage argument
            kwargs.setdefault("start_stage", start_stage)
        elif start_stage is not None:
            raise ValueError(
                f"task '{self.name}' has stage_starts=false: its env cannot start in stage "
                f"{start_stage}."
            )
        return instantiate(kwargs, batch_size=batch, device=self.device)

    def start_states(self, stage: int | None) -> dict[str, Any] | None:
        """The env's ``start_states(stage)`` hook, or ``None`` where it has none."""
        hook = getattr(self.spec_env, "start_states", None)
        return None if hook is None else hook(stage)

    def _tagged(
        self, base: EnvBase, stage: int | None, next_value: TensorDictModuleBase | None, train: bool
    ) -> TransformedEnv:
        """``base`` with stage tags (stage ``stage``'s view), episode returns with ``train``."""
        gamma = 0.99 if stage is None else float(self.stage_cfg(stage).gamma)
        tags = StageTransform(
            base.stage_fn, base.num_stages, train_stage=stage, next_value=next_value, gamma=gamma
        )
        return TransformedEnv(base, Compose(tags, RewardSum()) if train else Compose(tags))

    def stage_env(
        self,
        stage: int,
        batch_size: int,
        next_value: TensorDictModuleBase | None = None,
        *,
        copies: int = 1,
    ) -> TransformedEnv:
        """Stage ``stage``'s training env, with the episode returns the training logs read."""
        base = self.base_env(batch_size * copies, start_stage=stage)
        return self._tagged(base, stage, next_value, True)

    def stage_eval_env(
        self, stage: int, next_value: TensorDictModuleBase | None = None, *, copies: int = 1
    ) -> TransformedEnv:
        """Stage ``stage``'s evaluation env: every start state, else ``eval_episodes`` starts."""
        starts = self.start_states(stage)
        if starts is not None:
            base = self.base_env(**tile_starts(starts, copies))
        else:
            base = self.base_env(int(self.stage_cfg(stage).eval_episodes) * copies, stage)
        return self._tagged(base, stage, next_value, False)

    def task_env(
        self, batch_size: int | None = None, *, train: bool = False, copies: int = 1, **overrides
    ) -> TransformedEnv:
        """Whole-task env (stage tags only), with ``task.eval_env`` starts unless overridden:
        one element per start state with ``batch_size=None``, episode returns with ``train``."""
        eval_env = self.cfg.get("eval_env") or {}
        kwargs = {**OmegaConf.to_container(OmegaConf.create(eval_env), resolve=True), **overrides}
        if batch_size is None:
            starts = self.start_states(None)
            if starts is None:
                raise ValueError(f"the env of task '{self.name}' cannot enumerate its starts.")
            kwargs = {**tile_starts(starts, copies), **kwargs}
        else:
            kwargs["batch_size"] = batch_size * copies
        return self._tagged(self.base_env(**kwargs), None, None, train)

    def specs(self, stage: int) -> StageSpecs:
        """Observation and action entries of ``stage``'s learner, read from the env's specs."""
        env = self.spec_env
        if hasattr(env, "stage_observation_keys"):
            obs_keys = list(env.stage_observation_keys(stage))
        else:  # not the stage tag nor the success flag: what evaluations read
            obs_keys = [
                k for k in env.observation_spec.keys(True, True) if k not in ("stage", SUCCESS_KEY)
            ]
        hook = getattr(env, "stage_action_key", None)
        action_key = env.action_key if hook is None else hook(stage)
        obs_spec = env.observation_spec_unbatched
        shapes = [tuple(obs_spec[k].shape) for k in obs_keys]
        obs_dim = sum(s[-1] for s in shapes if len(s) == 1)
        action_spec = env.full_action_spec_unbatched[action_key]
        return StageSpecs(obs_keys, obs_dim, action_key, action_spec, shapes)
