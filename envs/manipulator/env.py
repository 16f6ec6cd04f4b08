"""The two-link precision manipulator (batched, torch-native): a coarse, then a fine stage."""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import StageStarts, draw_until

__all__ = ["ManipulatorEnv", "forward_kinematics", "inverse_kinematics", "wrap_angle"]

REACH = 2.0  # L1 + L2: radius of the reachable disk
MIN_RADIUS = 1e-3  # fine-stage starts closer than this to the base are rejected (IK singularity)


def wrap_angle(theta: torch.Tensor) -> torch.Tensor:
    """Angles wrapped to ``(-pi, pi]``."""
    wrapped = math.pi - torch.remainder(math.pi - theta, 2.0 * math.pi)
    return torch.where(wrapped <= -math.pi, wrapped + 2.0 * math.pi, wrapped)


def forward_kinematics(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Elbow and effector positions ``([..., 2], [..., 2])`` of joint angles ``[..., 2]``
    (links of length 1).

    Examples:
        >>> import math, torch
        >>> from torchrl_stages.envs import forward_kinematics
        >>> elbow, effector = forward_kinematics(torch.tensor([0.0, math.pi / 2]))
        >>> elbow.tolist(), [round(v, 6) for v in effector.tolist()]
        ([1.0, 0.0], [1.0, 1.0])
    """
    t1 = theta[..., 0]
    t12 = t1 + theta[..., 1]
    elbow = torch.stack([torch.cos(t1), torch.sin(t1)], -1)
    effector = elbow + torch.stack([torch.cos(t12), torch.sin(t12)], -1)
    return elbow, effector


def inverse_kinematics(points: torch.Tensor, elbow_up: bool | torch.Tensor = True) -> torch.Tensor:
    """Joint angles ``[..., 2]`` placing the effector at ``points [..., 2]``.

    ``elbow_up`` (a bool or a bool tensor) picks the solution with ``theta2 <= 0``, else
    ``theta2 >= 0``. A point farther than 2 gets the arm stretched towards it.

    Examples:
        >>> import torch
        >>> from torchrl_stages.envs import forward_kinematics, inverse_kinematics
        >>> theta = inverse_kinematics(torch.tensor([[1.0, 1.0], [1.0, 1.0]]),
        ...                            torch.tensor([True, False]))
        >>> [[round(v, 4) for v in row] for row in theta.tolist()]
        [[1.5708, -1.5708], [0.0, 1.5708]]
        >>> (forward_kinematics(theta)[1] - 1.0).abs().max().item() < 1e-6
        True
    """
    x, y = points[..., 0], points[..., 1]
    c2 = ((x * x + y * y - 2.0) / 2.0).clamp(-1.0, 1.0)
    s2 = torch.sqrt((1.0 - c2 * c2).clamp_min(0.0))
    up = torch.as_tensor(elbow_up, dtype=torch.bool, device=points.device)
    s2 = torch.where(up, -s2, s2)
    theta2 = torch.atan2(s2, c2)
    theta1 = torch.atan2(y, x) - torch.atan2(s2, 1.0 + c2)
    return wrap_angle(torch.stack(torch.broadcast_tensors(theta1, theta2), -1))


def _per_stage(name: str, value: Sequence[float]) -> tuple[float, ...]:
    """Validates one positive float per stage: ``(coarse, fine)``, or ``(single,)``."""
    values = tuple(float(v) for v in value)
    if len(values) not in (1, 2) or not all(v > 0 for v in values):
        raise ValueError(
            f"{name} must be one positive number per stage, (coarse, fine) or (single,); "
            f"got {value!r}."
        )
    return values


class ManipulatorEnv(StageStarts, EnvBase):
    """Two-link planar arm (links of length 1) steering its effector onto a target.

    The action ``a in [-1, 1]^2`` moves the joint angles by ``u_max[stage] * a``. Stage 0
    (coarse) lasts until the effector-target distance ``d`` drops below ``switch_distance``,
    stage 1 (fine) the rest of the episode; ``d <= success_distance`` gives reward 1 and
    ``terminated``. The observation ``[*B, 6]`` is elbow, effector and ``(target - effector) /
    scales[stage]``; the env writes ``"stage"``. One value per stage in ``u_max`` and ``scales``
    makes a single-stage task. ``start_stage=1`` starts within ``switch_distance`` of the target;
    ``random_target`` draws a target per reset. ``docs/tasks/manipulator.md`` has the details.

    Examples:
        >>> import torch
        >>> from torchrl_stages.envs import ManipulatorEnv, wrap_angle
        >>> env = ManipulatorEnv((4,), start_stage=1)
        >>> td = env.reset()
        >>> td["stage"].squeeze(-1).tolist(), bool((env.distance < 0.2).all())
        ([1, 1, 1, 1], True)
        >>> td["action"] = torch.tensor([[1.0, 0.0]]).expand(4, 2)
        >>> theta = env.theta
        >>> td = env.step(td)
        >>> delta = wrap_angle(env.theta - theta)  # the fine stage moves by 0.05 per unit action
        >>> torch.allclose(delta, torch.tensor([0.05, 0.0]).expand(4, 2), atol=1e-6)
        True
    """

    stage_fn = None  # the env writes "stage": StageTransform(None, n) reads it
    _dynamic_state = ("_theta", "_target", "_stage", "_steps")

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size = (),
        *,
        target: Sequence[float] = (1.0, 1.0),
        random_target: bool = False,
        u_max: Sequence[float] = (0.25, 0.05),
        scales: Sequence[float] = (0.5, 0.05),
        switch_distance: float = 0.2,
        success_distance: float = 0.01,
        max_steps: int = 50,
        start_stage: int | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        tgt = tuple(float(v) for v in target)
        if len(tgt) != 2 or math.hypot(*tgt) > REACH:
            raise ValueError(f"target must be a point (x, y) with |target| <= 2, got {target!r}.")
        self.target = tgt
        self.random_target = bool(random_target)
        self.u_max = _per_stage("u_max", u_max)
        self.scales = _per_stage("scales", scales)
        if len(self.u_max) != len(self.scales):
            raise ValueError(f"u_max {u_max!r} and scales {scales!r} must have the same length.")
        self.num_stages = len(self.u_max)
        self.switch_distance = float(switch_distance)
        self.success_distance = float(success_distance)
        if not 0.0 < self.success_distance < self.switch_distance:
            raise ValueError(
                "need 0 < success_distance < switch_distance, got "
                f"success_distance={success_distance}, switch_distance={switch_distance}."
            )
        bs, dev, f32 = self.batch_size, self.device, torch.float32
        self._n = n = bs.numel()
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, 6), dtype=f32, device=dev),
            stage=Categorical(self.num_stages, shape=(*bs, 1), dtype=torch.int64, device=dev),
            shape=bs,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*bs, 2), dtype=f32, device=dev)
        self._init_state(
            max_steps,
            _u_max_t=torch.tensor(self.u_max, dtype=f32, device=dev),
            _scales_t=torch.tensor(self.scales, dtype=f32, device=dev),
            _theta=torch.zeros(n, 2, dtype=f32, device=dev),
            _target=torch.tensor(tgt, dtype=f32, device=dev).expand(n, 2).clone(),
            _stage=torch.zeros(n, dtype=torch.int64, device=dev),
        )
        self.start_stage = start_stage

    def _rand(self, *shape: int) -> torch.Tensor:
        return torch.rand(shape, device=self.device, generator=self.rng)

    def _sample_targets(self) -> torch.Tensor:
        """One target per element, ``[n, 2]``: area-uniform in the disk of radius 2."""
        if not self.random_target:
            return self._target.new_tensor(self.target).expand(self._n, 2)
        r = REACH * torch.sqrt(self._rand(self._n))
        phi = 2.0 * math.pi * self._rand(self._n)
        return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], -1)

    def _candidates(self, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Candidate start angles ``[n, 2]`` and whether each one is acceptable ``[n]``."""
        n = self._n
        if self._start_stage == 1:
            rho = self.switch_distance * torch.sqrt(self._rand(n))
            phi = 2.0 * math.pi * self._rand(n)
            points = targets + rho.unsqueeze(-1) * torch.stack([torch.cos(phi), torch.sin(phi)], -1)
            theta = inverse_kinematics(points, self._rand(n) < 0.5)
            radius = points.norm(dim=-1)
            d = (targets - forward_kinematics(theta)[1]).norm(dim=-1)
            ok = (radius <= REACH) & (radius >= MIN_RADIUS) & (d < self.switch_distance)
            return theta, ok & (d > self.success_distance)
        theta = math.pi - 2.0 * math.pi * self._rand(n, 2)  # uniform on (-pi, pi]
        d = (targets - forward_kinematics(theta)[1]).norm(dim=-1)
        return theta, d >= self.switch_distance

    def observation_of(
        self, theta: torch.Tensor, target: torch.Tensor, stage: torch.Tensor, kinematics=None
    ) -> torch.Tensor:
        """The observation ``[..., 6]`` of joint angles ``[..., 2]`` reaching for ``target``
        ``[..., 2]`` in ``stage`` (int64 ``[...]``); ``kinematics``: their
        :func:`forward_kinematics`, where computed already."""
        elbow, eff = forward_kinematics(theta) if kinematics is None else kinematics
        diff = (target - eff) / self._scales_t[stage].unsqueeze(-1)
        return torch.cat([elbow, eff, diff], -1)

    def _observe(self, kinematics=None, **flags: torch.Tensor) -> TensorDict:
        bs = self.batch_size
        observation = self.observation_of(self._theta, self._target, self._stage, kinematics)
        return TensorDict(
            observation=observation.reshape(*bs, 6),
            stage=self._stage.reshape(*bs, 1).clone(),
            **flags,
            batch_size=bs,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = self._reset_mask(tensordict)
        targets = torch.where(mask.unsqueeze(-1), self._sample_targets(), self._target)
        what = f"start states (start_stage={self._start_stage}; is switch_distance sensible?)"
        self._theta.copy_(draw_until(partial(self._candidates, targets), self._theta, mask, what))
        self._target.copy_(targets)
        self._stage.masked_fill_(mask, 1 if self._start_stage == 1 else 0)
        self._steps.masked_fill_(mask, 0)
        return self._observe(**self._reset_flags())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").reshape(self._n, 2).to(self._theta.dtype)
        step = self._u_max_t[self._stage].unsqueeze(-1) * action.clamp(-1.0, 1.0)
        self._theta.copy_(wrap_angle(self._theta + step))
        kinematics = forward_kinematics(self._theta)  # the hot path computes them once
        d = (self._target - kinematics[1]).norm(dim=-1)
        if self.num_stages > 1:
            self._stage.copy_(torch.where(d < self.switch_distance, 1, self._stage))
        return self._observe(kinematics, **self._step_flags(d <= self.success_distance))

    def stage_observation_keys(self, stage: int) -> list[str]:
        """Network inputs of every stage: only ``"observation"`` (``"stage"`` is a tag)."""
        return ["observation"]

    def set_state(
        self,
        theta: Sequence[float] | torch.Tensor,
        *,
        target: Sequence[float] | torch.Tensor | None = None,
        stage: int | torch.Tensor | None = None,
    ) -> TensorDictBase:
        """Puts every element in a given state, like a reset; returns the reset's TensorDict.

        ``theta`` and ``target`` are a pair or one per element (``[*B, 2]``); ``target``
        defaults to the current targets, ``stage`` to the stage of the distance.
        """
        self._theta.copy_(wrap_angle(self._pairs("theta", theta, self._theta.dtype)))
        if target is not None:
            self._target.copy_(self._pairs("target", target, self._theta.dtype))
        if stage is None:
            self._stage.copy_(
                (self._distance() < self.switch_distance).long() * (self.num_stages - 1)
            )
        else:
            stage = torch.as_tensor(stage, dtype=torch.int64, device=self.device)
            if ((stage < 0) | (stage >= self.num_stages)).any():
                raise ValueError(f"stage must be in [0, {self.num_stages}), got {stage.tolist()}.")
            self._stage.copy_(stage.expand(*self.batch_size, 1).reshape(self._n))
        self._steps.zero_()
        return self._observe(**self._reset_flags())

    def _distance(self) -> torch.Tensor:
        return (self._target - forward_kinematics(self._theta)[1]).norm(dim=-1)

    @property
    def theta(self) -> torch.Tensor:
        """Current joint angles, ``[*B, 2]`` (a copy)."""
        return self._theta.reshape(*self.batch_size, 2).clone()

    @property
    def targets(self) -> torch.Tensor:
        """Current targets, ``[*B, 2]`` (a copy)."""
        return self._target.reshape(*self.batch_size, 2).clone()

    @property
    def stage(self) -> torch.Tensor:
        """Current stages, int64 ``[*B, 1]`` (a copy)."""
        return self._stage.reshape(*self.batch_size, 1).clone()

    @property
    def effector(self) -> torch.Tensor:
        """Current effector positions, ``[*B, 2]``."""
        return forward_kinematics(self._theta)[1].reshape(*self.batch_size, 2)

    @property
    def distance(self) -> torch.Tensor:
        """Current effector-target distances, ``[*B, 1]``."""
        return self._distance().reshape(*self.batch_size, 1)
