"""Stage awareness as a TorchRL transform."""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical, Composite
from torchrl.envs import Transform

StageFn = Callable[[TensorDictBase], torch.Tensor]


class NonFiniteValueError(FloatingPointError):
    """The next stage's value of a transition is NaN or infinite."""


def freeze(module: nn.Module) -> nn.Module:
    """Returns a frozen snapshot of ``module``: a deep copy with no gradients, in eval mode."""
    module = copy.deepcopy(module)
    module.requires_grad_(False)
    return module.eval()


class StageTransform(Transform):
    """Tags every TensorDict with its stage and rewrites stage-transition rewards.

    The stage of a state comes from ``stage_fn`` (a callable mapping a TensorDict to an int64
    tensor of shape ``[*batch, 1]``). Stages only move forward: the stage after a step is
    ``max(stage_t, stage_fn(next))``.

    The transform writes ``stage_key`` (root and ``"next"``, declared in the observation spec) and
    ``transition_key`` (true on the step where the stage index increases). In *training mode for
    stage k* (``train_stage=k``), the step that leaves stage k ends stage k's episode
    (``terminated`` and ``done`` are set) and its reward becomes
    ``r + gamma * V_{k+1}(s_{t+1})``, where ``V_{k+1}`` is a frozen copy of ``next_value`` (a module
    writing ``value_key``). No value term is added when the task itself terminates on that step;
    truncation is left alone.

    Appended to a replay buffer, :meth:`forward` rewrites ``("next", reward)`` of sampled
    transitions from the stored stage entries instead (the storage stays raw), which lets the
    next-stage value change after the data was collected.

    Args:
        stage_fn: maps a TensorDict (a reset output or the ``"next"`` content of a step) to its
            stage index, int64 ``[*batch, 1]``. ``None`` reads the env's own ``stage_key`` entry
            (for envs whose dynamics track the stage themselves).
        num_stages: number of stages N; stage indices are ``0..N-1``.

    Keyword Args:
        train_stage: the stage being learned, or ``None`` to only tag (whole-task rollouts).
        next_value: state-value module of stage ``train_stage + 1`` (see
            :mod:`torchrl_stages.values`). It is frozen (copied, no grad, eval mode) here.
        gamma: stage ``train_stage``'s discount.
        rewrite_in_env: finish stage k's view inside ``env.step``. With ``False`` the env only
            ends the episode at the transition (``done``) and keeps the raw reward and
            ``terminated``; a copy of this transform appended to the replay buffer finishes them
            at sampling time with the then-current ``next_value``.
        stage_key, transition_key, reward_key, terminated_key, done_key, value_key: keys.

    Examples:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> from torchrl_stages.transforms import StageTransform
        >>> base = GridWorldEnv(batch_size=(4,))
        >>> env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
        >>> td = env.rollout(3)
        >>> td["stage"].shape, td["next", "stage_transition"].dtype
        (torch.Size([4, 3, 1]), torch.bool)
    """

    def __init__(
        self,
        stage_fn: StageFn | None,
        num_stages: int,
        *,
        train_stage: int | None = None,
        next_value: TensorDictModuleBase | None = None,
        gamma: float = 0.99,
        rewrite_in_env: bool = True,
        stage_key: NestedKey = "stage",
        transition_key: NestedKey = "stage_transition",
        reward_key: NestedKey = "reward",
        terminated_key: NestedKey = "terminated",
        done_key: NestedKey = "done",
        value_key: NestedKey = "state_value",
    ) -> None:
        if num_stages < 1:
            raise ValueError(f"num_stages must be >= 1, got {num_stages}.")
        if train_stage is not None and not 0 <= train_stage < num_stages:
            raise ValueError(f"train_stage={train_stage} is outside 0..{num_stages - 1}.")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma={gamma} is outside (0, 1].")
        if next_value is not None and (train_stage is None or train_stage == num_stages - 1):
            raise ValueError(
                "next_value is only used when training a stage that has a next stage: "
                f"got train_stage={train_stage} with num_stages={num_stages}."
            )
        super().__init__(in_keys=[], out_keys=[stage_key, transition_key])
        self.stage_fn = stage_fn
        self.num_stages = num_stages
        self.train_stage = train_stage
        self.gamma = gamma
        self.rewrite_in_env = rewrite_in_env
        self.stage_key = stage_key
        self.transition_key = transition_key
        self.reward_key = reward_key
        self.terminated_key = terminated_key
        self.done_key = done_key
        self.value_key = value_key
        self.next_value = None
        self.set_next_value(next_value)

    def set_next_value(self, module: TensorDictModuleBase | None) -> None:
        """Installs a frozen snapshot of the next stage's value module (or removes it)."""
        self.next_value = None if module is None else freeze(module)

    def train(self, mode: bool = True) -> StageTransform:
        # env.train()/env.eval() propagate here: the frozen value network stays in eval mode.
        super().train(mode)
        if self.next_value is not None:
            self.next_value.eval()
        return self

    # ------------------------------------------------------------------ helpers
    def _stage(self, td: TensorDictBase) -> torch.Tensor:
        stage = td.get(self.stage_key) if self.stage_fn is None else self.stage_fn(td)
        return stage.to(torch.int64).reshape(*td.batch_size, 1)

    @torch.no_grad()
    def _value(self, next_td: TensorDictBase) -> torch.Tensor:
        # Run the value module on a selection so it cannot write into the env's output.
        td_in = next_td.select(*self.next_value.in_keys).clone(False)
        return self.next_value(td_in).get(self.value_key)

    def _learner_view(
        self, stage_t: torch.Tensor, next_td: TensorDictBase, *, finish: bool
    ) -> None:
        """Stage k's learner view of a step (``next_td`` is the t+1 content).

        The step that leaves stage k is ``done`` for the collector. When ``finish`` is set it is
        also ``terminated`` for stage k's loss, and its reward gains gamma_k * V_{k+1}(s_{t+1})
        unless the task itself terminated on that step.
        """
        leaving = next_td.get(self.transition_key) & (stage_t == self.train_stage)
        next_td.set(self.done_key, next_td.get(self.done_key) | leaving)
        if not finish:
            return
        task_terminated = next_td.get(self.terminated_key)
        if self.next_value is not None and leaving.any():
            bootstrap = leaving & ~task_terminated
            reward = next_td.get(self.reward_key)
            value = self._value(next_td).to(reward.dtype).reshape(reward.shape)
            if not bool(torch.isfinite(value[bootstrap]).all()):
                raise NonFiniteValueError(
                    f"the value of stage {self.train_stage + 1}, V(s_t+1), is not finite on a "
                    f"transition out of stage {self.train_stage}: stage {self.train_stage + 1}'s "
                    "networks diverged, so stage "
                    f"{self.train_stage}'s transition rewards would be NaN or infinite"
                )
            next_td.set(
                self.reward_key, torch.where(bootstrap, reward + self.gamma * value, reward)
            )
        next_td.set(self.terminated_key, task_terminated | leaving)

    # ------------------------------------------------------------------ env path
    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        # Rows that are not reset get their previous values back in EnvBase.reset.
        stage = self._stage(tensordict_reset)
        tensordict_reset.set(self.stage_key, stage)
        tensordict_reset.set(self.transition_key, torch.zeros_like(stage, dtype=torch.bool))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        stage_t = tensordict.get(self.stage_key)
        stage_next = torch.maximum(self._stage(next_tensordict), stage_t)
        transition = stage_next > stage_t
        next_tensordict.set(self.stage_key, stage_next)
        next_tensordict.set(self.transition_key, transition)
        if self.train_stage is not None:
            self._learner_view(stage_t, next_tensordict, finish=self.rewrite_in_env)
        return next_tensordict

    # ------------------------------------------------------------------ replay-buffer path
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Finishes stage k's view of stored transitions (replay-buffer transform).

        Use it on data collected with ``rewrite_in_env=False``: the storage keeps the raw reward
        and the task's own ``terminated``; each sample gets the transition marked terminal and
        ``gamma_k * V_{k+1}(s_{t+1})`` from the *current* ``next_value`` module.
        """
        if self.train_stage is None:
            return tensordict
        self._learner_view(tensordict.get(self.stage_key), tensordict.get("next"), finish=True)
        return tensordict

    # ------------------------------------------------------------------ specs
    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = (*observation_spec.shape, 1)
        device = observation_spec.device
        observation_spec[self.stage_key] = Categorical(
            self.num_stages, shape=shape, dtype=torch.int64, device=device
        )
        observation_spec[self.transition_key] = Categorical(
            2, shape=shape, dtype=torch.bool, device=device
        )
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_stages={self.num_stages}, train_stage={self.train_stage}, "
            f"gamma={self.gamma}, next_value={'set' if self.next_value is not None else None})"
        )
