"""What a multi-stage env gives this package, written down: :class:`StageEnv` (what every task's
env has) and :class:`StageEnvHooks` (what an env may add, each hook with what it changes).

A task's env is a torchrl ``EnvBase`` (a gymnasium env: through
:class:`~torchrl_stages.gym_env.GymStageEnv`, which has all of :class:`StageEnv`). The task
builds it from its config as ``Env(batch_size=..., device=..., start_stage=..., **task.env)``;
``start_stage`` (``None``: the task's own starts; ``k``: starts inside stage ``k``) is left out
for a task with ``stage_starts: false``, which then trains with the joint or flat schedule.

Examples:
    >>> from torchrl_stages.envs import GridWorldEnv
    >>> env = GridWorldEnv((2,))
    >>> isinstance(env, StageEnv), env.num_stages
    (True, 5)
    >>> [hook for hook in ("start_states", "stage_action_key") if hasattr(env, hook)]
    ['start_states']
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

__all__ = ["StageEnv", "StageEnvHooks"]


@runtime_checkable
class StageEnv(Protocol):
    """What every multi-stage env has, besides torchrl's ``EnvBase``.

    Attributes:
        num_stages: the stages 0..N-1 its states go through, in order.
    """

    num_stages: int

    def stage_fn(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The stage of each state of ``tensordict`` (what a step returns, or its ``"next"``):
        int64 ``[*batch, 1]``, never lower than the stage of the state before it.
        :class:`~torchrl_stages.transforms.StageTransform` tags every TensorDict with it. An
        env that writes its own ``"stage"`` entry sets ``stage_fn = None``."""
        ...


@runtime_checkable
class StageEnvHooks(Protocol):
    """What a multi-stage env may add; each hook is optional (an env has any of them), and the
    package asks for each with ``getattr`` / ``hasattr``.

    Attributes:
        max_steps: the time limit of an episode; evaluations cap their episodes there
            (default 1000).
        can_step_finished: ``True`` where stepping a finished element is legal and changes
            nothing else (fixed starts): whole-task evaluations then step on instead of
            resetting (:func:`~torchrl_stages.evaluate.can_step_finished`).
    """

    max_steps: int
    can_step_finished: bool

    def start_states(self, stage: int | None) -> dict[str, Any] | None:
        """Constructor arguments whose batch starts at every start state of ``stage`` once
        (``None``: the task's own starts), or ``None`` where they cannot be listed: stage
        evaluations then run from each start instead of ``eval_episodes`` random ones."""
        ...

    def stage_observation_keys(self, stage: int) -> Sequence[NestedKey]:
        """The observation entries stage ``stage``'s learner reads (default: every observation
        but the stage tag and the success flag)."""
        ...

    def stage_action_key(self, stage: int) -> NestedKey:
        """The action entry stage ``stage``'s policy writes, where the stages act through
        entries of their own (default: the env's ``action_key``)."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """The env's running state and random generator, so that a stage resumed from a
        checkpoint goes on with the same episodes (``load_state_dict`` restores it; see
        :class:`~torchrl_stages.envs.StageStarts`). Without them a resumed stage restarts its
        episodes."""
        ...
