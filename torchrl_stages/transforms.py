"""Stage awareness as TorchRL transforms: the stage tag of every step, and stage k's view of its
transitions (the step that leaves stage k bootstrapped from stage k+1's value)."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase, unravel_key
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
    """The env returned a non-finite ``key`` that the next stage's value reads."""

    def __init__(self, key: NestedKey, stage: int) -> None:
        self.key = key
        super().__init__(
            f"the env returned a non-finite {key!r} on a transition out of stage {stage}"
        )


def freeze(module: nn.Module) -> nn.Module:
    """A frozen snapshot of ``module``: a deep copy with no gradients, in eval mode."""
    return copy.deepcopy(module).requires_grad_(False).eval()


class _StageView(Transform):
    """What both stage transforms share: their checks and stage ``stage``'s view of transitions."""

    def __init__(
        self,
        stage: int | None,
        num_stages: int,
        gamma: float,
        next_value: TensorDictModuleBase | None,
        standalone: bool,
        out_keys: list[NestedKey],
    ) -> None:
        if num_stages < 1:
            raise ValueError(f"num_stages must be >= 1, got {num_stages}.")
        if stage is not None and not 0 <= stage < num_stages:
            raise ValueError(f"stage {stage} is outside 0..{num_stages - 1}.")
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma={gamma} is outside (0, 1].")
        has_next = stage is not None and stage < num_stages - 1
        if next_value is not None and not has_next:
            raise ValueError(
                "next_value is only used when training a stage that has a next stage: stage "
                f"{stage} is the last one or no stage is trained (num_stages={num_stages})."
            )
        if has_next and next_value is None and not standalone:
            raise ValueError(
                f"stage {stage} has a next stage: pass next_value (stage {stage + 1}'s state "
                "value, e.g. learner.value()) for its transition reward, or standalone=True to "
                "train the stage on its own rewards only."
            )
        super().__init__(in_keys=[], out_keys=out_keys)
        self.stage, self.num_stages, self.gamma = stage, num_stages, gamma

    @torch.no_grad()
    def _view(self, leaving: torch.Tensor, next_td: TensorDictBase) -> None:
        """In place on ``"next"``: a ``leaving`` transition is ``terminated`` and, unless the
        task terminated on it, gains ``gamma * next_value(s_{t+1})``."""
        stage, next_value = self.stage, self.next_value
        task_terminated = next_td.get("terminated")
        if next_value is not None and leaving.any():
            landed = next_td.get("stage")[leaving]
            if (landed != stage + 1).any():
                raise ValueError(
                    f"a transition out of stage {stage} landed in stage "
                    f"{landed[landed != stage + 1][0].item()}: with a next-stage value, a step "
                    f"may only move to stage {stage + 1} (whose value it gets)."
                )
            bootstrap = leaving & ~task_terminated
            reward = next_td.get("reward")
            # the value module runs on a selection: it cannot write into the transition
            inputs = next_td.select(*next_value.in_keys)
            value = next_value(inputs.clone(False)).get("state_value")
            value = value.to(reward.dtype).reshape(reward.shape)
            if not bool(torch.isfinite(value[bootstrap]).all()):
                for key, entry in inputs.items(True, True):
                    if entry.is_floating_point() and not bool(torch.isfinite(entry).all()):
                        raise NonFiniteInputError(unravel_key(("next", key)), stage)
                raise NonFiniteValueError(
                    f"the value of stage {stage + 1}, V(s_t+1), is not finite on a transition "
                    f"out of stage {stage}: stage {stage + 1}'s networks diverged, so stage "
                    f"{stage}'s transition rewards would be NaN or infinite"
                )
            next_td.set("reward", torch.where(bootstrap, reward + self.gamma * value, reward))
        terminated = task_terminated | leaving
        next_td.set("terminated", terminated)
        # an env without a truncated entry keeps its own done
        next_td.set("done", terminated | next_td.get("truncated", next_td.get("done")))

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(stage={self.stage}, num_stages={self.num_stages}, "
            f"gamma={self.gamma}, next_value={'set' if self.next_value is not None else None})"
        )


class StageTransform(_StageView):
    """Tags every step with its stage and, training stage k, gives stage k's view of it.

    ``stage_fn(td)`` gives each state's stage, int64 ``[*batch, 1]`` (``None``: the env's own
    ``"stage"`` entry); stages only move forward. With ``train_stage=k`` the step that leaves
    stage k ends its episode: it is ``terminated`` and gains ``gamma * V_{k+1}(s_{t+1})`` from a
    frozen copy of ``next_value``, unless the task terminated on it (``standalone=True``: never).
    With ``rewrite_in_env=False`` it is ``truncated`` instead and stays raw for a
    :class:`StageRewardTransform`; in both modes leaving stage k counts as solved.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_stages.envs import GridWorldEnv
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
    ) -> None:
        out_keys = ["stage", "stage_transition"]
        super().__init__(train_stage, num_stages, gamma, next_value, standalone, out_keys)
        self.stage_fn = stage_fn
        self.rewrite_in_env = rewrite_in_env
        self.set_next_value(next_value)

    @property
    def train_stage(self) -> int | None:
        return self.stage

    def set_next_value(self, module: TensorDictModuleBase | None) -> None:
        self.next_value = None if module is None else freeze(module)

    def train(self, mode: bool = True) -> StageTransform:
        super().train(mode)
        if self.next_value is not None:  # the frozen value network stays in eval mode
            self.next_value.eval()
        return self

    @property
    def _writes_success(self) -> bool:
        # leaving stage k is a truncation, which ended_well would count as failed
        return self.stage is not None and not self.rewrite_in_env

    def _stage(self, td: TensorDictBase) -> torch.Tensor:
        stage = td.get("stage") if self.stage_fn is None else self.stage_fn(td)
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
        """Ends stage k's episode where a step leaves stage k, and marks it solved."""
        leaving = next_td.get("stage_transition") & (stage_t == self.stage)
        success = next_td.get(SUCCESS_KEY, None)
        if success is not None:  # leaving stage k is stage k's success, unless the task failed
            failed = next_td.get("terminated") & ~success
            next_td.set(SUCCESS_KEY, success | (leaving & ~failed))
        if self.rewrite_in_env:
            self._view(leaving, next_td)
            return
        if success is None:
            next_td.set(SUCCESS_KEY, next_td.get("terminated") | leaving)
        truncated = next_td.get("truncated") | leaving
        next_td.set("truncated", truncated)
        next_td.set("done", next_td.get("terminated") | truncated)

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        stage = self._stage(tensordict_reset)
        no = torch.zeros_like(stage, dtype=torch.bool)
        tensordict_reset.set("stage", stage)
        tensordict_reset.set("stage_transition", no)
        if self._writes_success and SUCCESS_KEY not in tensordict_reset.keys(True):
            tensordict_reset.set(SUCCESS_KEY, no.clone())
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        stage_t = tensordict.get("stage")
        stage_next = torch.maximum(self._stage(next_tensordict), stage_t)
        next_tensordict.set("stage", stage_next)
        next_tensordict.set("stage_transition", stage_next > stage_t)
        if self.stage is not None:
            self._learner_view(stage_t, next_tensordict)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "StageTransform is an env transform (it tags steps as they happen). To compute stage "
            "k's view of stored transitions, append StageRewardTransform(k, ...) to the replay "
            "buffer instead."
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        def spec(n: int, dtype: torch.dtype) -> Categorical:
            shape = (*observation_spec.shape, 1)
            return Categorical(n, shape=shape, dtype=dtype, device=observation_spec.device)

        observation_spec["stage"] = spec(self.num_stages, torch.int64)
        observation_spec["stage_transition"] = spec(2, torch.bool)
        if self._writes_success and SUCCESS_KEY not in observation_spec.keys(True):
            observation_spec[SUCCESS_KEY] = spec(2, torch.bool)
        return observation_spec


class StageRewardTransform(_StageView):
    """Stage k's view of replay-buffer samples, from the *current* next-stage value: the
    transitions that leave stage k are ``terminated`` with ``r + gamma * V_{k+1}(s_{t+1})``,
    so the next stage may keep learning after the data was stored (the joint schedule).
    ``next_value`` is held by reference, never copied nor trained here.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> v1 = TensorDictModule(lambda o: o + 1, ["observation"], ["state_value"])
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(4), batch_size=2)
        >>> _ = rb.append_transform(StageRewardTransform(0, 2, next_value=v1, gamma=0.5))
        >>> leaves = torch.tensor([[True], [False]])  # the first transition enters stage 1
        >>> no = torch.zeros(2, 1, dtype=torch.bool)
        >>> _ = rb.extend(TensorDict(stage=torch.zeros(2, 1, dtype=torch.long), next=TensorDict(
        ...     observation=torch.ones(2, 1), stage=leaves.long(), stage_transition=leaves,
        ...     reward=torch.zeros(2, 1), terminated=no, truncated=no, done=no,
        ...     batch_size=[2]), batch_size=[2]))
        >>> nxt = rb[:]["next"]  # the storage stays raw; samples get stage 0's view
        >>> nxt["reward"].squeeze(-1).tolist(), nxt["terminated"].squeeze(-1).tolist()
        ([1.0, 0.0], [True, False])
    """

    def __init__(
        self,
        stage: int,
        num_stages: int,
        *,
        next_value: TensorDictModuleBase | None = None,
        standalone: bool = False,
        gamma: float = 0.99,
    ) -> None:
        super().__init__(stage, num_stages, gamma, next_value, standalone, [])
        # not a sub-module: the next stage's learner owns it, not this (or the buffer's) state_dict
        self.__dict__["next_value"] = next_value

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        needed = ["stage_transition", "reward", "terminated"]
        needed += ["stage"] if self.next_value is not None else []
        required = ["stage", *(("next", key) for key in needed)]
        missing = [k for k in required if tensordict.get(k, None) is None]
        if missing:
            names = ", ".join(".".join(k) if isinstance(k, tuple) else k for k in missing)
            raise KeyError(
                f"StageRewardTransform(stage={self.stage}) needs {names} in the sampled data: "
                'store transitions collected through StageTransform (it writes "stage" and '
                '("next", "stage_transition")), keeping those entries in the buffer.'
            )
        nxt = tensordict.get("next")
        self._view(nxt.get("stage_transition") & (tensordict.get("stage") == self.stage), nxt)
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        raise RuntimeError(
            "StageRewardTransform is a replay-buffer transform: append it to a replay buffer "
            "(rb.append_transform). In an env, StageTransform(train_stage=k, next_value=...) "
            "gives stage k's view as the steps happen."
        )

    _step = _reset  # an env step is refused the same way


class StageDiscount(Transform):
    """Discounts every stored transition with the gamma of its stage in torchrl's estimators.

    ``steps_to_next_obs = log(gammas[stage]) / log(gamma)`` makes a TD(0) estimator built with
    ``gamma`` bootstrap with ``gammas[stage(s_t)]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> t = StageDiscount([0.9, 0.99], gamma=0.99)
        >>> td = t(TensorDict(stage=torch.tensor([[0], [1]]), batch_size=[2]))
        >>> (0.99 ** td["steps_to_next_obs"]).squeeze(-1)
        tensor([0.9000, 0.9900])
    """

    def __init__(self, gammas: Sequence[float], gamma: float) -> None:
        if not 0.0 < gamma < 1.0 and any(g != gamma for g in gammas):
            raise ValueError(f"gamma={gamma} cannot express the stage discounts {list(gammas)}.")
        super().__init__(in_keys=["stage"], out_keys=["steps_to_next_obs"])
        ratio = [1.0 if g == gamma else math.log(g) / math.log(gamma) for g in gammas]
        self.register_buffer("_steps", torch.tensor(ratio, dtype=torch.float32))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        stage = tensordict.get(self.in_keys[0])
        return tensordict.set(self.out_keys[0], self._steps.to(stage.device)[stage])

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase):
        raise RuntimeError("StageDiscount transforms stored transitions, not env steps.")
