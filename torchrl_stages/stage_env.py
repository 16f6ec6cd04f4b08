"""The env protocol: what every task's env has (:class:`StageEnv`) and may add
(:class:`StageEnvHooks`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


@runtime_checkable
class StageEnv(Protocol):
    """What every multi-stage env has besides ``EnvBase``: its stages ``0..num_stages-1``.

    A task builds it as ``Env(batch_size=..., device=..., start_stage=..., **task.env)``;
    ``start_stage`` (``None``: the task's own starts; ``k``: inside stage k) is left out for a
    task with ``stage_starts: false``.

    Examples:
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> env = GridWorldEnv((2,))
        >>> isinstance(env, StageEnv), env.num_stages, isinstance(env, StageEnvHooks)
        (True, 5, False)
    """

    num_stages: int

    def stage_fn(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The stage of each state, int64 ``[*batch, 1]``, never below the state before it
        (``stage_fn = None`` where the env writes its own ``"stage"`` entry)."""


@runtime_checkable
class StageEnvHooks(Protocol):
    """What a multi-stage env may add; each hook is optional and asked for with ``hasattr``.

    Attributes:
        max_steps: the time limit of an episode, where evaluations cap theirs (default 1000).
        can_step_finished: ``True`` where stepping a finished element is legal and changes
            nothing else (fixed starts): whole-task evaluations then step on instead of resetting.
    """

    max_steps: int
    can_step_finished: bool

    def start_states(self, stage: int | None) -> dict[str, Any] | None:
        """Constructor arguments whose batch starts once at every start state of ``stage``
        (``None``: the task's own), or ``None``: evaluations then use random starts."""

    def stage_observation_keys(self, stage: int) -> Sequence[NestedKey]:
        """What stage ``stage``'s learner reads (default: every observation but ``"stage"`` and
        the success flag)."""

    def stage_action_key(self, stage: int) -> NestedKey:
        """What stage ``stage``'s policy writes (default: the env's ``action_key``)."""

    def state_dict(self) -> dict[str, Any]:
        """The env's running state and generator, for a resume with the same episodes."""
