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
    """The constructor arguments of :meth:`StagedTask.start_states` for ``copies`` consecutive
    copies of its batch: ``batch_size`` times ``copies``, and every tensor whose first
    dimension is the batch repeated along it (the per-element starts); the rest unchanged.

    Examples:
        >>> starts = {"batch_size": (2,), "start_cell": torch.tensor([[0, 0], [1, 0]]), "x": 3}
        >>> tiled = tile_starts(starts, 2)
        >>> tiled["batch_size"], tiled["start_cell"][:, 0].tolist(), tiled["x"]
        ((4,), [0, 1, 0, 1], 3)
    """
    if copies == 1:
        return starts
    (size,) = tuple(starts["batch_size"])
    out = dict(starts, batch_size=(size * copies,))
    for key, value in starts.items():
        if isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == size:
            out[key] = value.repeat(copies, *[1] * (value.ndim - 1))
    return out


class StagedTask:
    """Makes the envs of a task config (``cfg.task``) for training and evaluation.

    The env named by ``task.env._target_`` must be a batched TorchRL ``EnvBase`` that accepts
    ``batch_size``, ``start_stage`` (``None``: whole-task starts) and ``device`` keyword
    arguments and has ``num_stages`` and ``stage_fn(tensordict)``. Optional hooks for tasks whose
    stages differ: ``stage_action_key(k)`` and ``stage_observation_keys(k)``.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": {"gamma": 0.9}, "b": {"gamma": 0.9}},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> task.stage_env(1, batch_size=4).rollout(2, break_when_any_done=False)["stage"].shape
        torch.Size([4, 2, 1])
    """

    def __init__(self, cfg: DictConfig, device: str | torch.device = "cpu") -> None:
        self.cfg = cfg
        self.device = torch.device(device)
        self.stage_names: list[str] = list(cfg.stages.keys())
        self._spec_env = self.base_env(batch_size=1)

    @staticmethod
    def env_num_stages(cfg: DictConfig) -> int:
        """The ``num_stages`` of the env that the task config ``cfg`` builds (built once, on
        the CPU, and closed)."""
        env = StagedTask(cfg).spec_env
        try:
            return int(env.num_stages)
        finally:
            env.close()

    @property
    def spec_env(self) -> EnvBase:
        """The env built with ``batch_size=1`` whose specs the learners are built from."""
        return self._spec_env

    @property
    def name(self) -> str:
        return str(self.cfg.name)

    @property
    def num_stages(self) -> int:
        return int(self._spec_env.num_stages)

    def stage_cfg(self, stage: int) -> DictConfig:
        return self.cfg.stages[self.stage_names[stage]]

    def base_env(
        self, batch_size: int | Sequence[int], start_stage: int | None = None, **overrides: Any
    ) -> EnvBase:
        """The task's env without stage transform (``overrides`` go to its constructor)."""
        batch = (int(batch_size),) if isinstance(batch_size, int) else tuple(batch_size)
        kwargs = OmegaConf.to_container(self.cfg.env, resolve=True)
        kwargs.update(overrides)
        if self.stage_starts:  # an env without stage starts takes no start_stage argument
            kwargs.setdefault("start_stage", start_stage)
        elif start_stage is not None:
            raise ValueError(
                f"task '{self.name}' has stage_starts=false: its env cannot start in stage "
                f"{start_stage}."
            )
        return instantiate(kwargs, batch_size=batch, device=self.device)

    @property
    def stage_starts(self) -> bool:
        """Whether the env can start episodes inside a chosen stage (``task.stage_starts``)."""
        return bool(self.cfg.get("stage_starts", True))

    def start_states(self, stage: int | None) -> dict[str, Any] | None:
        """Constructor arguments that start every batch element at one of ``stage``'s start
        states, all of them covered (``None``: the whole-task starts), from the env's optional
        ``start_states(stage)`` hook; ``None`` when the env cannot enumerate them."""
        hook = getattr(self._spec_env, "start_states", None)
        return None if hook is None else hook(stage)

    def stage_env(
        self,
        stage: int,
        batch_size: int,
        next_value: TensorDictModuleBase | None = None,
        *,
        all_starts: bool = False,
        episode_returns: bool = True,
        copies: int = 1,
    ) -> TransformedEnv:
        """Stage ``stage``'s training env: starts inside the stage, its learner's view of rewards.

        Episodes end when they leave the stage; the transition reward adds
        ``gamma_stage * next_value(s_{t+1})``. With ``episode_returns`` a ``RewardSum`` tracks
        episode returns (``("next", "episode_reward")``, what the training logs read). With
        ``all_starts`` (and an env that enumerates its starts, see :meth:`start_states`) the
        batch holds one element per start state of the stage and ``batch_size`` is ignored.
        ``copies``: the batch holds that many consecutive copies of it (one per seed of a
        seed-stacked learner, :func:`tile_starts`).
        """
        starts = self.start_states(stage) if all_starts else None
        if starts is not None:
            base = self.base_env(**tile_starts(starts, copies))
        else:
            base = self.base_env(batch_size * copies, start_stage=stage)
        transform = StageTransform(
            base.stage_fn,
            base.num_stages,
            train_stage=stage,
            next_value=next_value,
            gamma=float(self.stage_cfg(stage).gamma),
        )
        transforms = [transform, RewardSum()] if episode_returns else [transform]
        return TransformedEnv(base, Compose(*transforms))

    def stage_eval_env(
        self, stage: int, next_value: TensorDictModuleBase | None = None, *, copies: int = 1
    ) -> TransformedEnv:
        """The env of stage ``stage``'s greedy evaluations: one episode from every start state
        when the env enumerates them, else ``eval_episodes`` random starts in the stage (no
        ``RewardSum``: evaluations compute their returns from the rollout)."""
        cfg = self.stage_cfg(stage)
        return self.stage_env(
            stage,
            int(cfg.eval_episodes),
            next_value,
            all_starts=True,
            episode_returns=False,
            copies=copies,
        )

    def task_env(
        self,
        batch_size: int | None = None,
        *,
        train: bool = False,
        copies: int = 1,
        **overrides: Any,
    ) -> TransformedEnv:
        """Whole-task env (stage tags only), with ``task.eval_env`` starts unless overridden.

        ``batch_size=None`` gives one element per whole-task start state (the env must
        enumerate them, see :meth:`start_states`). ``train`` adds ``RewardSum`` (episode
        returns for the training logs). ``copies``: the batch holds that many consecutive
        copies of it (one per seed of a seed-stacked learner, :func:`tile_starts`).
        """
        eval_env = self.cfg.get("eval_env") or {}
        kwargs = {**OmegaConf.to_container(OmegaConf.create(eval_env), resolve=True), **overrides}
        if batch_size is None:
            starts = self.start_states(None)
            if starts is None:
                raise ValueError(f"the env of task '{self.name}' cannot enumerate its starts.")
            kwargs = {**tile_starts(starts, copies), **kwargs}
        else:
            kwargs["batch_size"] = batch_size * copies
        base = self.base_env(**kwargs)
        tags = StageTransform(base.stage_fn, base.num_stages)
        return TransformedEnv(base, Compose(tags, RewardSum()) if train else tags)

    def specs(self, stage: int) -> StageSpecs:
        """Observation and action entries of ``stage``'s learner, read from the env's specs."""
        env = self._spec_env
        if hasattr(env, "stage_observation_keys"):
            obs_keys = list(env.stage_observation_keys(stage))
        else:
            # every observation but the stage tag (an env that writes "stage" itself) and the
            # success flag (what evaluations read, not what a policy sees)
            obs_keys = [
                k for k in env.observation_spec.keys(True, True) if k not in ("stage", SUCCESS_KEY)
            ]
        action_key = (
            env.stage_action_key(stage) if hasattr(env, "stage_action_key") else (env.action_key)
        )
        obs_spec = env.observation_spec_unbatched
        shapes = [tuple(obs_spec[k].shape) for k in obs_keys]
        obs_dim = sum(s[-1] for s in shapes if len(s) == 1)
        action_spec = env.full_action_spec_unbatched[action_key]
        return StageSpecs(obs_keys, obs_dim, action_key, action_spec, shapes)
