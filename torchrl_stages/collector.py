"""A batched-env collector whose whole state is a ``state_dict``, so a stage resumes exactly."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

log = logging.getLogger("torchrl_stages")


class StageCollector:
    """Yields ``[*env.batch_size, T]`` batches of ``frames_per_batch`` env steps.

    It collects like torchrl's ``Collector`` on a batched env (``step_and_maybe_reset``,
    uniformly random actions from the action spec for the first ``init_random_frames``, then
    ``policy`` under the random exploration type) and adds what that collector cannot restore
    (its ``load_state_dict`` starts fresh trajectories): the running episodes. :meth:`state_dict`
    holds the frame count, the carried TensorDict of the next step (observations, episode
    returns of wrappers such as ``RewardSum``) and the env's own state (its dynamics and random
    generator, through ``env.base_env.state_dict()``), so an interrupted stage continues from
    the same episodes, bitwise, on envs that put their state in ``state_dict`` (the shipped
    envs, ``torchrl_stages.envs._common.StageStarts``; gymnasium envs that draw from their
    ``np_random``, :class:`~torchrl_stages.gym_env.GymStageEnv`). Other envs restart their
    episodes, with a warning.

    Args:
        env: a batched env (``env.batch_size`` is ``[num_envs]``).
        policy: the exploration policy.

    Keyword Args:
        frames_per_batch: env frames per batch (a multiple of the env's batch size).
        total_frames: the budget; iteration stops once this many frames were collected.
        init_random_frames: frames of uniformly random actions before the policy acts.

    Examples:
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> from tensordict.nn import TensorDictModule
        >>> import torch
        >>> env = GridWorldEnv((4,))
        >>> policy = TensorDictModule(lambda o: torch.zeros(o.shape[:-1], dtype=torch.long),
        ...                           ["observation"], ["action"])
        >>> collector = StageCollector(env, policy, frames_per_batch=8, total_frames=16)
        >>> [batch.shape for batch in collector]
        [torch.Size([4, 2]), torch.Size([4, 2])]
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        *,
        frames_per_batch: int,
        total_frames: int,
        init_random_frames: int = 0,
    ) -> None:
        num_envs = env.batch_size.numel()
        if len(env.batch_size) != 1:
            raise ValueError(
                f"StageCollector needs an env with one batch dimension [num_envs], got "
                f"batch_size={list(env.batch_size)}; wrap a single env in a batched one "
                "(e.g. torchrl's SerialEnv/ParallelEnv) or build it with batch_size=(n,)."
            )
        if frames_per_batch % num_envs:
            raise ValueError(
                f"frames_per_batch={frames_per_batch} is not a multiple of the env's batch "
                f"size {num_envs}."
            )
        self.env, self.policy = env, policy
        self.frames_per_batch, self.total_frames = frames_per_batch, total_frames
        self.init_random_frames = init_random_frames
        self.frames = 0
        self._carrier: TensorDictBase | None = None

    def __iter__(self) -> Iterator[TensorDictBase]:
        steps_per_batch = self.frames_per_batch // self.env.batch_size.numel()
        while self.frames < self.total_frames:
            if self._carrier is None:
                self._carrier = self.env.reset()
            random = self.frames < self.init_random_frames
            steps = []
            with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                for _ in range(steps_per_batch):
                    td = self._carrier
                    td = self.env.rand_action(td) if random else self.policy(td)
                    td, self._carrier = self.env.step_and_maybe_reset(td)
                    steps.append(td)
            batch = torch.stack(steps, dim=-1)
            self.frames += batch.numel()
            yield batch

    @property
    def restorable(self) -> bool:
        """Whether the env keeps its dynamic state in ``state_dict`` (``get_extra_state``)."""
        base = getattr(self.env, "base_env", self.env)
        return type(base).get_extra_state is not torch.nn.Module.get_extra_state

    def state_dict(self) -> dict[str, Any]:
        """Frames so far and, on restorable envs, the carried TensorDict of the next step and
        the env's state."""
        state: dict[str, Any] = {"frames": self.frames}
        if self.restorable and self._carrier is not None:
            state["carrier"] = self._carrier.to_dict()
            state["env"] = getattr(self.env, "base_env", self.env).state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores the frame count and, where the state holds them, the env's state and the
        running episodes. Where it does not (an env that keeps no state in ``state_dict``), or
        the env could not rebuild them (``episodes_rebuilt`` false, see
        :class:`~torchrl_stages.gym_env.GymStageEnv`), the episodes start over: that is
        logged, since the run then differs from an uninterrupted one."""
        self.frames = int(state["frames"])
        self._carrier = None  # without a saved env state, the episodes start over
        base = getattr(self.env, "base_env", self.env)
        if "env" in state:
            base.load_state_dict(state["env"])
            if getattr(base, "episodes_rebuilt", True):
                self._carrier = TensorDict(state["carrier"], self.env.batch_size)
        elif self.frames:
            log.warning(
                "resume: the checkpoint holds no state of the env %s (%s): its episodes start "
                "over, so this run is not bitwise equal to an uninterrupted one "
                "(docs/guides/bring-your-own-env.md, Resume)",
                type(base).__name__,
                "it keeps none in state_dict, get_extra_state"
                if not self.restorable
                else "written by a version that did not keep it",
            )
