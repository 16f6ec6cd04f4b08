"""Stage awareness as a TorchRL transform."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence
from typing import Protocol

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical, Composite
from torchrl.envs import Transform

StageFn = Callable[[TensorDictBase], torch.Tensor]

# an env's own success flag (torchrl's convention, e.g. LIBERO's): bool, [*batch, 1]
SUCCESS_KEY = "success"


class NonFiniteValueError(FloatingPointError):
    """The next stage's value of a transition is NaN or infinite."""


class NonFiniteInputError(NonFiniteValueError):
    """The next stage's value is not finite because its input, an entry of s_{t+1} that the
    env returned, is NaN or infinite (the env's fault, not the networks').

    Attributes:
        key: the env's entry that is not finite.
    """

    def __init__(self, key: NestedKey, stage: int) -> None:
        self.key = key
        super().__init__(
            f"the env returned a non-finite {key!r} on a transition out of stage {stage}"
        )


class _Keys(Protocol):
    stage_key: NestedKey
    transition_key: NestedKey
    reward_key: NestedKey
    terminated_key: NestedKey
    truncated_key: NestedKey
    done_key: NestedKey
    value_key: NestedKey


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


@torch.no_grad()
def apply_stage_view(
    stage: int,
    gamma: float,
    next_value: TensorDictModuleBase | None,
    stage_t: torch.Tensor,
    next_td: TensorDictBase,
    keys: _Keys,
) -> None:
    """Stage ``stage``'s learner view of transitions, in place on their ``"next"`` content.

    A transition that leaves stage ``stage`` is ``terminated`` for its loss (``done`` follows,
    as ``terminated | truncated``) and its reward gains ``gamma * next_value(s_{t+1})``, unless
    the task itself terminated on it. It must land in the next stage: ``next_value`` is that
    stage's value, and a non-finite one raises :class:`NonFiniteValueError`.
    """
    leaving = next_td.get(keys.transition_key) & (stage_t == stage)
    task_terminated = next_td.get(keys.terminated_key)
    if next_value is not None and leaving.any():
        landed = next_td.get(keys.stage_key)[leaving]
        if (landed != stage + 1).any():
            raise ValueError(
                f"a transition out of stage {stage} landed in stage "
                f"{landed[landed != stage + 1][0].item()}: with a next-stage value, a step may "
                f"only move to stage {stage + 1} (whose value it gets)."
            )
        bootstrap = leaving & ~task_terminated
        reward = next_td.get(keys.reward_key)
        # the value module runs on a selection: it cannot write into the transition
        td_in = next_td.select(*next_value.in_keys).clone(False)
        value = next_value(td_in).get(keys.value_key).to(reward.dtype).reshape(reward.shape)
        if not bool(torch.isfinite(value[bootstrap]).all()):
            for key, entry in next_td.select(*next_value.in_keys).items(True, True):
                if entry.is_floating_point() and not bool(torch.isfinite(entry).all()):
                    raise NonFiniteInputError(("next", *_as_tuple(key)), stage)
            raise NonFiniteValueError(
                f"the value of stage {stage + 1}, V(s_t+1), is not finite on a transition out "
                f"of stage {stage}: stage {stage + 1}'s networks diverged, so stage {stage}'s "
                "transition rewards would be NaN or infinite"
            )
        next_td.set(keys.reward_key, torch.where(bootstrap, reward + gamma * value, reward))
    terminated = task_terminated | leaving
    next_td.set(keys.terminated_key, terminated)
    truncated = next_td.get(keys.truncated_key, None)
    if truncated is None:  # an env without a truncated entry
        next_td.set(keys.done_key, next_td.get(keys.done_key) | terminated)
    else:
        next_td.set(keys.done_key, terminated | truncated)


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

    Stage indices must be in ``0..N-1`` and, when a next-stage value is set, a step may move
    one stage at most. To compute stage k's view of stored transitions at sampling time instead
    (the joint schedule), collect with ``rewrite_in_env=False`` or tag only, and append a
    :class:`StageRewardTransform` to the replay buffer.

    Args:
        stage_fn: maps a TensorDict (a reset output or the ``"next"`` content of a step) to its
            stage index, int64 ``[*batch, 1]``. ``None`` reads the env's own ``stage_key`` entry
            (for envs whose dynamics track the stage themselves).
        num_stages: number of stages N; stage indices are ``0..N-1``.

    Keyword Args:
        train_stage: the stage being learned, or ``None`` to only tag (whole-task rollouts).
        next_value: state-value module of stage ``train_stage + 1`` (see
            :mod:`torchrl_stages.values`). It is frozen (copied, no grad, eval mode) here.
            Required when ``train_stage < N - 1``, unless ``standalone``.
        standalone: train stage ``train_stage < N - 1`` on its own rewards only (no value
            term on the transition), e.g. to test a stage alone.
        gamma: stage ``train_stage``'s discount.
        rewrite_in_env: finish stage k's view inside ``env.step``. With ``False`` the env only
            cuts the episode at the transition (``truncated`` and ``done``) and keeps the raw
            reward and ``terminated``; a :class:`StageRewardTransform` on the replay buffer
            finishes them at sampling time with the then-current next-stage value.
        stage_key: the stage tag's key.
        transition_key: the transition flag's key (under ``"next"``).
        reward_key: the reward's key.
        terminated_key: the termination flag's key.
        done_key: the done flag's key.
        value_key: the key the next stage's value module writes.
        success_key: the env's success flag, if it writes one (evaluations count an episode
            as solved by it, :func:`~torchrl_stages.evaluate.ended_well`): in training mode
            for stage k the step that leaves stage k sets it. Without ``rewrite_in_env`` the
            transform writes it where the env does not (``terminated``, or leaving stage k), so
            an episode that leaves stage k counts as solved in both modes.

    Examples:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> from torchrl_stages.transforms import StageTransform
        >>> base = GridWorldEnv(batch_size=(4,))
        >>> env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
        >>> td = env.rollout(3, break_when_any_done=False)
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
        standalone: bool = False,
        gamma: float = 0.99,
        rewrite_in_env: bool = True,
        stage_key: NestedKey = "stage",
        transition_key: NestedKey = "stage_transition",
        reward_key: NestedKey = "reward",
        terminated_key: NestedKey = "terminated",
        truncated_key: NestedKey = "truncated",
        done_key: NestedKey = "done",
        value_key: NestedKey = "state_value",
        success_key: NestedKey = SUCCESS_KEY,
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
        has_next = train_stage is not None and train_stage < num_stages - 1
        if has_next and next_value is None and not standalone:
            raise ValueError(
                f"train_stage={train_stage} has a next stage: pass next_value (stage "
                f"{train_stage + 1}'s state value, e.g. learner.value()) for its transition "
                "reward, or standalone=True to train the stage on its own rewards only."
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
        self.truncated_key = truncated_key
        self.done_key = done_key
        self.value_key = value_key
        self.success_key = success_key
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
        stage = stage.to(torch.int64).reshape(*td.batch_size, 1)
        bad = (stage < 0) | (stage >= self.num_stages)
        if bad.any():
            source = "the env's stage entry" if self.stage_fn is None else "stage_fn"
            raise ValueError(
                f"{source} gave stage {stage[bad][0].item()}, outside 0..{self.num_stages - 1} "
                f"(num_stages={self.num_stages})."
            )
        return stage

    def _learner_view(self, stage_t: torch.Tensor, next_td: TensorDictBase) -> None:
        """Stage k's learner view of a step (``next_td`` is the t+1 content).

        The step that leaves stage k ends stage k's episode. With ``rewrite_in_env`` it is
        ``terminated`` for stage k's loss and its reward gains gamma_k * V_{k+1}(s_{t+1}) unless
        the task itself terminated on that step; otherwise it is ``truncated`` (the stored
        transition stays raw for a :class:`StageRewardTransform`). ``done`` follows. Where the
        env writes a ``success_key`` entry, the step that leaves stage k sets it (stage k's
        episode is solved) unless the task terminated on it unsolved; without
        ``rewrite_in_env`` and an env flag, the transform writes one (``terminated | leaving``).
        """
        leaving = next_td.get(self.transition_key) & (stage_t == self.train_stage)
        success = next_td.get(self.success_key, None)
        if success is not None:  # leaving stage k is stage k's success, unless the task failed
            failed = next_td.get(self.terminated_key) & ~success
            next_td.set(self.success_key, success | (leaving & ~failed))
        if not self.rewrite_in_env:
            if success is None:  # leaving is a truncation below: the flag says it was solved
                next_td.set(self.success_key, next_td.get(self.terminated_key) | leaving)
            truncated = next_td.get(self.truncated_key) | leaving
            next_td.set(self.truncated_key, truncated)
            next_td.set(self.done_key, next_td.get(self.terminated_key) | truncated)
            return
        apply_stage_view(self.train_stage, self.gamma, self.next_value, stage_t, next_td, self)

    # ------------------------------------------------------------------ env path
    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        # Rows that are not reset get their previous values back in EnvBase.reset.
        stage = self._stage(tensordict_reset)
        tensordict_reset.set(self.stage_key, stage)
        tensordict_reset.set(self.transition_key, torch.zeros_like(stage, dtype=torch.bool))
        if self._writes_success and self.success_key not in tensordict_reset.keys(True):
            tensordict_reset.set(self.success_key, torch.zeros_like(stage, dtype=torch.bool))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        stage_t = tensordict.get(self.stage_key)
        stage_next = torch.maximum(self._stage(next_tensordict), stage_t)
        transition = stage_next > stage_t
        next_tensordict.set(self.stage_key, stage_next)
        next_tensordict.set(self.transition_key, transition)
        if self.train_stage is not None:
            self._learner_view(stage_t, next_tensordict)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "StageTransform is an env transform (it tags steps as they happen). To compute stage "
            "k's view of stored transitions, append StageRewardTransform(k, ...) to the replay "
            "buffer instead."
        )

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
        if self._writes_success and self.success_key not in observation_spec.keys(True):
            observation_spec[self.success_key] = Categorical(
                2, shape=shape, dtype=torch.bool, device=device
            )
        return observation_spec

    @property
    def _writes_success(self) -> bool:
        """Training stage k without ``rewrite_in_env`` on an env with no success flag: the
        transform writes one (``terminated``, or leaving stage k), since leaving stage k is then
        a truncation, which :func:`~torchrl_stages.evaluate.ended_well` would count as failed."""
        return self.train_stage is not None and not self.rewrite_in_env

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(num_stages={self.num_stages}, train_stage={self.train_stage}, "
            f"gamma={self.gamma}, next_value={'set' if self.next_value is not None else None})"
        )


class StageRewardTransform(Transform):
    """Stage k's learner view of sampled transitions, computed when they are sampled.

    A replay-buffer transform, kept apart from the env transforms the way torchrl keeps
    ``MultiStepTransform``: the storage holds raw transitions tagged by :class:`StageTransform`
    (``"stage"`` at the root and under ``"next"``, ``("next", "stage_transition")``), and every
    sample gets the transitions that leave stage k marked ``terminated`` with
    ``r + gamma_k * V_{k+1}(s_{t+1})`` from the *current* ``next_value``: the next stage may
    keep learning after the data was stored (the paper's joint schedule, Algorithm 1).

    Args:
        stage: the stage k whose loss reads the samples.
        num_stages: number of stages N.

    Keyword Args:
        next_value: state-value module of stage k + 1, held by reference (not copied, never
            trained here): pass ``learner.value(live=True)`` to follow the next learner's target
            networks as they move. Required when ``k < N - 1`` unless ``standalone``.
        standalone: stage ``k < N - 1`` learns from its own rewards only.
        gamma: stage k's discount.
        stage_key: the stage tag's key.
        transition_key: the transition flag's key (under ``"next"``).
        reward_key: the reward's key.
        terminated_key: the termination flag's key.
        truncated_key: the truncation flag's key.
        done_key: the done flag's key.
        value_key: the key the next stage's value module writes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> v1 = TensorDictModule(lambda o: o.sum(-1, keepdim=True), ["observation"],
        ...                       ["state_value"])
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(4), batch_size=2)
        >>> _ = rb.append_transform(StageRewardTransform(0, 2, next_value=v1, gamma=0.5))
        >>> leaves = torch.tensor([[True], [False]])  # the first transition enters stage 1
        >>> no = torch.zeros(2, 1, dtype=torch.bool)
        >>> _ = rb.extend(TensorDict(stage=torch.zeros(2, 1, dtype=torch.long), next=TensorDict(
        ...     observation=torch.ones(2, 2), stage=leaves.long(), stage_transition=leaves,
        ...     reward=torch.zeros(2, 1), terminated=no, truncated=no, done=no,
        ...     batch_size=[2]), batch_size=[2]))
        >>> sample = rb[:]  # the storage stays raw; samples get stage 0's view
        >>> nxt = sample["next"]
        >>> nxt["reward"].squeeze(-1).tolist(), nxt["terminated"].squeeze(-1).tolist()
        ([1.0, 0.0], [True, False])
    """

    ENV_ERR = (
        "StageRewardTransform is a replay-buffer transform: append it to a replay buffer "
        "(rb.append_transform). In an env, StageTransform(train_stage=k, next_value=...) gives "
        "stage k's view as the steps happen."
    )

    def __init__(
        self,
        stage: int,
        num_stages: int,
        *,
        next_value: TensorDictModuleBase | None = None,
        standalone: bool = False,
        gamma: float = 0.99,
        stage_key: NestedKey = "stage",
        transition_key: NestedKey = "stage_transition",
        reward_key: NestedKey = "reward",
        terminated_key: NestedKey = "terminated",
        truncated_key: NestedKey = "truncated",
        done_key: NestedKey = "done",
        value_key: NestedKey = "state_value",
    ) -> None:
        if not 0 <= stage < num_stages:
            raise ValueError(f"stage={stage} is outside 0..{num_stages - 1}.")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma={gamma} is outside (0, 1].")
        if stage == num_stages - 1 and next_value is not None:
            raise ValueError(f"stage {stage} is the last one: it has no next_value.")
        if stage < num_stages - 1 and next_value is None and not standalone:
            raise ValueError(
                f"stage {stage} has a next stage: pass next_value (stage {stage + 1}'s state "
                "value) or standalone=True."
            )
        super().__init__(in_keys=[], out_keys=[])
        self.stage, self.num_stages, self.gamma = stage, num_stages, gamma
        self.stage_key, self.transition_key = stage_key, transition_key
        self.reward_key, self.terminated_key = reward_key, terminated_key
        self.truncated_key, self.done_key, self.value_key = truncated_key, done_key, value_key
        # held by reference, not as a sub-module: it belongs to the next stage's learner, and
        # must not travel in this transform's (or the replay buffer's) state_dict
        self.__dict__["next_value"] = next_value

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.parent is not None:
            raise RuntimeError(self.ENV_ERR)
        required = [self.stage_key, ("next", self.transition_key), ("next", self.reward_key)]
        required.append(("next", self.terminated_key))
        if self.next_value is not None:
            required.append(("next", self.stage_key))
        missing = [k for k in required if tensordict.get(k, None) is None]
        if missing:
            names = ", ".join(".".join(k) if isinstance(k, tuple) else k for k in missing)
            raise KeyError(
                f"StageRewardTransform(stage={self.stage}) needs {names} in the sampled data: "
                'store transitions collected through StageTransform (it writes "stage" and '
                '("next", "stage_transition")), keeping those entries in the buffer.'
            )
        apply_stage_view(
            self.stage,
            self.gamma,
            self.next_value,
            tensordict.get(self.stage_key),
            tensordict.get("next"),
            self,
        )
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(self.ENV_ERR)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        raise RuntimeError(self.ENV_ERR)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase):
        raise RuntimeError(self.ENV_ERR)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(stage={self.stage}, num_stages={self.num_stages}, "
            f"gamma={self.gamma}, next_value={'set' if self.next_value is not None else None})"
        )


class StageDiscount(Transform):
    """Discounts every transition with the gamma of its stage in torchrl's value estimators.

    It writes ``steps_to_next_obs = log(gammas[stage(s_t)]) / log(gamma)`` next to each stored
    transition; a TD(0) estimator built with ``gamma`` then bootstraps with
    ``gamma ** steps_to_next_obs = gammas[stage(s_t)]``. One learner trained on the whole task
    (the flat baseline) so optimizes the same stage-discounted objective as the stacked
    learners. Use it as a replay-buffer transform or on collected batches.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> t = StageDiscount([0.9, 0.99], gamma=0.99)
        >>> td = t(TensorDict(stage=torch.tensor([[0], [1]]), batch_size=[2]))
        >>> (0.99 ** td["steps_to_next_obs"]).squeeze(-1)
        tensor([0.9000, 0.9900])
    """

    def __init__(
        self,
        gammas: Sequence[float],
        gamma: float,
        *,
        stage_key: NestedKey = "stage",
        out_key: NestedKey = "steps_to_next_obs",
    ) -> None:
        if not 0.0 < gamma < 1.0 and any(g != gamma for g in gammas):
            raise ValueError(f"gamma={gamma} cannot express the stage discounts {list(gammas)}.")
        super().__init__(in_keys=[stage_key], out_keys=[out_key])
        ratio = [1.0 if g == gamma else math.log(g) / math.log(gamma) for g in gammas]
        self.register_buffer("_steps", torch.tensor(ratio, dtype=torch.float32))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        stage = tensordict.get(self.in_keys[0])
        return tensordict.set(self.out_keys[0], self._steps.to(stage.device)[stage])

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase):
        raise RuntimeError("StageDiscount transforms stored transitions, not env steps.")
