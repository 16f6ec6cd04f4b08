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
    """Yields ``[num_envs, T]`` batches of ``frames_per_batch`` steps of a batched env, as
    torchrl's ``Collector`` does (random actions for the first ``init_random_frames``). Its
    :meth:`state_dict` holds the running episodes of an env that keeps its state in
    ``state_dict``, so a resumed stage continues bitwise (others restart their episodes).

    Examples:
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> policy = TensorDictModule(lambda o: torch.zeros(o.shape[:-1], dtype=torch.long),
        ...                           ["observation"], ["action"])
        >>> collector = StageCollector(GridWorldEnv((4,)), policy, frames_per_batch=8,
        ...                            total_frames=16)
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
        self._base: EnvBase = getattr(env, "base_env", env)
        # whether the env keeps its dynamic state in ``state_dict`` (``get_extra_state``)
        self.restorable = type(self._base).get_extra_state is not torch.nn.Module.get_extra_state
        self.frames_per_batch, self.total_frames = frames_per_batch, total_frames
        self.init_random_frames = init_random_frames
        self.frames = 0
        self._carrier: TensorDictBase | None = None

    def __iter__(self) -> Iterator[TensorDictBase]:
        steps_per_batch = self.frames_per_batch // self.env.batch_size.numel()
        while self.frames < self.total_frames:
            if self._carrier is None:
                self._carrier = self.env.reset()
            act = self.env.rand_action if self.frames < self.init_random_frames else self.policy
            steps = []
            with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                for _ in range(steps_per_batch):
                    td, self._carrier = self.env.step_and_maybe_reset(act(self._carrier))
                    steps.append(td)
            batch = torch.stack(steps, dim=-1)
            self.frames += batch.numel()
            yield batch

    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {"frames": self.frames}
        if self.restorable and self._carrier is not None:
            state.update(carrier=self._carrier.to_dict(), env=self._base.state_dict())
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.frames = int(state["frames"])
        self._carrier = None  # without a saved env state, the episodes start over
        base = self._base
        if "env" in state:
            base.load_state_dict(state["env"])
            if getattr(base, "episodes_rebuilt", True):
                self._carrier = TensorDict(state["carrier"], self.env.batch_size)
        elif self.frames:
            why = "written by a version that did not keep it"
            if not self.restorable:
                why = "it keeps none in state_dict, get_extra_state"
            log.warning(
                f"resume: the checkpoint holds no state of the env {type(base).__name__} ({why}): "
                "its episodes start over, so this run is not bitwise equal to an uninterrupted "
                "one (docs/guides/bring-your-own-env.md, Resume)"
            )
