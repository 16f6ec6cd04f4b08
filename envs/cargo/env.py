"""Cooperative cargo transport (batched, torch-native): slider robot, then self-propelled robot."""

from __future__ import annotations

import math
from collections.abc import Sequence
from importlib import resources
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import StageStarts, sparse_reward_and_done_specs
from ..manipulator.env import wrap_angle

__all__ = ["CargoEnv", "ROBOTS", "load_obstacle_map"]

#: robot kinds and what their action entry ``(kind, "action")`` is
ROBOTS = ("slider", "propelled")
MAX_ATTEMPTS = 100  # bound on the vectorized rejection-sampling loop of the starts
SEGMENT_SAMPLES = 16  # points checked along each move (spacing < 0.25 cell for moves < 4 a)


def load_obstacle_map(path: str | Path | None = None) -> torch.Tensor:
    """An obstacle map as a bool tensor ``[H, W]``, indexed ``[y, x]`` (row 0 is ``y = 0``).

    The text format has one line per row, top row (largest ``y``) first: ``#`` for an obstacle
    cell, ``.`` for a free one; lines starting with ``;`` are comments. ``None`` loads the map
    shipped with the package (``envs/cargo/data/cargo_map.txt``, 50 x 70).

    Examples:
        >>> from torchrl_stages.envs import load_obstacle_map
        >>> occupancy = load_obstacle_map()
        >>> occupancy.shape, occupancy.dtype, bool(occupancy[0, 0])
        (torch.Size([50, 70]), torch.bool, False)
    """
    if path is None:
        text = resources.files(__package__).joinpath("data", "cargo_map.txt").read_text()
    else:
        text = Path(path).read_text()
    rows = [line.strip() for line in text.splitlines()]
    rows = [row for row in rows if row and not row.startswith(";")]
    if not rows or len({len(row) for row in rows}) != 1 or set("".join(rows)) - {"#", "."}:
        raise ValueError(
            f"obstacle map {path or 'cargo_map.txt'}: expected equal-length rows of '#' and '.'."
        )
    grid = torch.tensor([[c == "#" for c in row] for row in rows], dtype=torch.bool)
    return grid.flip(0)


class CargoEnv(StageStarts, EnvBase):
    """Robots carrying a cargo across an obstacle map to a target, one robot per stage.

    Positions ``(x, y)`` are continuous, in units of the robot radius ``a`` (one map cell per
    ``a``); the robot is a point for collisions. The map is split by the vertical stage line
    ``x = W / 2``: stage 0 (left half) is driven by ``robots[0]``, stage 1 (right half) by
    ``robots[1]``. Stages never go back: once the cargo has crossed the line, the second robot
    keeps it even if noise pushes it back over the line. Per control step (Euler-Maruyama):

    * ``"slider"``: constant speed, continuous turning rate ``w = max_turn * a``, ``a`` in
      ``[-1, 1]`` (action ``("slider", "action")``, ``Bounded [*B, 1]``):
      ``x += L cos(theta) + n_x``, ``y += L sin(theta) + n_y``, ``theta += w + n_theta``.
    * ``"propelled"``: orientation only diffuses; binary propulsion ``v in {0, L}`` (action
      ``("propelled", "action")``, ``Categorical(2)``, ``[*B]``):
      ``x += v cos(theta) + n_x``, ``y += v sin(theta) + n_y``, ``theta += n_theta``.

    ``L = step_length``, ``n_x, n_y ~ N(0, translational_noise^2)``, ``n_theta ~
    N(0, rotational_noise^2)``. A move is rejected when one of 16 evenly spaced points of its
    segment (end point included, under 0.25 cell apart) lies on an obstacle cell or off the map:
    the position stays, the rotation still happens. No move passes through an obstacle; one may
    clip the corner of an obstacle cell. Each element applies the action
    of its stage's robot; a missing action entry counts as zeros. Reaching within
    ``success_radius`` of ``target`` gives reward 1 and ``terminated``; after ``max_steps``
    steps an element is ``truncated``.

    Observation entries (the networks read ``"window"`` and ``"target"``):

    * ``"window"``: ``uint8 [*B, 1, w, w]``, the obstacle map (off-map counts as obstacle) in
      the robot's frame, one cell per pixel: the robot sits at the center, heading up (row 0 is
      farthest ahead), its left on the left.
    * ``"target"``: ``float32 [*B, 2]``, the target in the robot's frame (ahead, left),
      divided by ``W / 2``.
    * ``"position"`` ``[*B, 2]`` and ``"heading"`` ``[*B, 1]``: the state, for plots and tests.
    * ``"stage"``: ``int64 [*B, 1]``, so :class:`~torchrl_stages.transforms.StageTransform`
      is used with ``stage_fn=None``.

    Args:
        batch_size: batch shape of the env; any shape, e.g. ``()``, ``(64,)``, ``(2, 3)``.

    Keyword Args:
        robots: one robot kind per stage: ``("slider", "propelled")`` is the paper's task;
            one robot (e.g. ``("propelled",)``) makes a single-stage baseline over the whole map
            with the same starts.
        map_file: obstacle map (see :func:`load_obstacle_map`); ``None``: the shipped map.
        target: target position ``(x, y)``, a free point right of the stage line.
        success_radius, step_length, translational_noise, rotational_noise: in ``a`` (and rad).
        max_turn: the slider's largest turn per step (rad).
        window: side of the observation window, in cells.
        max_steps: per-element time limit.
        start_stage: ``None`` or ``0``: uniform free positions in the left half (whole-task
            starts); ``1``: in the right half. Headings are uniform.
        device: torch device.

    Examples:
        >>> import torch
        >>> from torchrl_stages.envs import CargoEnv
        >>> env = CargoEnv((3,))
        >>> td = env.reset()
        >>> td["window"].shape, td["target"].shape, td["stage"].squeeze(-1).tolist()
        (torch.Size([3, 1, 10, 10]), torch.Size([3, 2]), [0, 0, 0])
        >>> td = env.set_state([[34.0, 2.0]], heading=0.0)  # facing the line, right before it
        >>> td["slider", "action"] = torch.zeros(3, 1)
        >>> env.step(td)["next", "stage"].squeeze(-1).tolist()  # 2 a later: the second robot
        [1, 1, 1]
    """

    stage_fn = None  # the env tracks its stage itself: StageTransform(None, n) reads "stage"

    _dynamic_state = ("_pos", "_theta", "_stage", "_steps")  # what a step changes (see StageStarts)

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size = (),
        *,
        robots: Sequence[str] = ROBOTS,
        map_file: str | None = None,
        target: Sequence[float] = (62.0, 36.0),
        success_radius: float = 2.0,
        step_length: float = 2.0,
        translational_noise: float = 0.163,
        rotational_noise: float = 0.447,
        max_turn: float = 1.0,
        window: int = 10,
        max_steps: int = 500,
        start_stage: int | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.robots = tuple(str(r) for r in robots)
        if not 1 <= len(self.robots) <= 2 or set(self.robots) - set(ROBOTS):
            raise ValueError(
                f"robots must be one or two of {ROBOTS} (one per stage), got {list(robots)}."
            )
        self.num_stages = len(self.robots)
        occupancy = load_obstacle_map(map_file)
        self.height, self.width = occupancy.shape
        self.stage_line = self.width / 2.0
        self.target = tuple(float(v) for v in target)
        if len(self.target) != 2 or not self.target[0] >= self.stage_line:
            raise ValueError(f"target must be a point (x, y) right of x = {self.stage_line}.")
        for name, value in (
            ("success_radius", success_radius),
            ("step_length", step_length),
            ("max_turn", max_turn),
        ):
            if not value > 0:
                raise ValueError(f"{name} must be positive, got {value}.")
        if translational_noise < 0 or rotational_noise < 0:
            raise ValueError("translational_noise and rotational_noise must be >= 0.")
        if window <= 0 or max_steps <= 0:
            raise ValueError(f"window and max_steps must be positive, got {window}, {max_steps}.")
        self.success_radius, self.step_length = float(success_radius), float(step_length)
        self.translational_noise = float(translational_noise)
        self.rotational_noise = float(rotational_noise)
        self.max_turn, self.window, self.max_steps = float(max_turn), int(window), int(max_steps)
        self._make_specs()
        dev, f32, n = self.device, torch.float32, self._n
        centers = (self.window - 1) / 2.0 - torch.arange(self.window, dtype=f32)
        ahead, left = torch.meshgrid(centers, centers, indexing="ij")  # row i ahead, column j left
        buffers = {  # non-persistent buffers: follow env.to(device), stay out of state_dict
            "_occupancy": occupancy.to(dev),
            "_offsets": torch.stack([ahead, left], -1).reshape(-1, 2).to(dev),  # [w*w, 2]
            "_target": torch.tensor(self.target, dtype=f32, device=dev),
            "_is_slider": torch.tensor([r == "slider" for r in self.robots], device=dev),
            "_pos": torch.zeros(n, 2, dtype=f32, device=dev),
            "_theta": torch.zeros(n, dtype=f32, device=dev),
            "_stage": torch.zeros(n, dtype=torch.int64, device=dev),
            "_steps": torch.zeros(n, dtype=torch.int64, device=dev),
        }
        for name, buf in buffers.items():
            self.register_buffer(name, buf, persistent=False)
        if self.blocked(self._target.unsqueeze(0)).item():
            raise ValueError(f"target {self.target} lies on an obstacle or off the map.")
        self.rng = None
        self.start_stage = start_stage

    def _make_specs(self) -> None:
        bs, dev, f32 = self.batch_size, self.device, torch.float32
        self._n = bs.numel()
        w = self.window
        self.observation_spec = Composite(
            window=Binary(shape=(*bs, 1, w, w), dtype=torch.uint8, device=dev),
            target=Unbounded(shape=(*bs, 2), dtype=f32, device=dev),
            position=Unbounded(shape=(*bs, 2), dtype=f32, device=dev),
            heading=Unbounded(shape=(*bs, 1), dtype=f32, device=dev),
            stage=Categorical(self.num_stages, shape=(*bs, 1), dtype=torch.int64, device=dev),
            shape=bs,
        )
        actions = {
            "slider": Bounded(-1.0, 1.0, shape=(*bs, 1), dtype=f32, device=dev),
            "propelled": Categorical(2, shape=bs, dtype=torch.int64, device=dev),
        }
        self.action_spec = Composite(
            {r: Composite(action=actions[r], shape=bs) for r in dict.fromkeys(self.robots)},
            shape=bs,
        )
        self.reward_spec, self.done_spec = sparse_reward_and_done_specs(bs, dev)

    # ------------------------------------------------------------------ geometry
    @property
    def occupancy(self) -> torch.Tensor:
        """The obstacle map, bool ``[H, W]`` indexed ``[y, x]``."""
        return self._occupancy

    def blocked(self, points: torch.Tensor) -> torch.Tensor:
        """Whether points ``[..., 2]`` lie on an obstacle cell or off the map (bool ``[...]``)."""
        x, y = points[..., 0], points[..., 1]
        inside = (x >= 0) & (x < self.width) & (y >= 0) & (y < self.height)
        col = x.floor().long().clamp(0, self.width - 1)
        row = y.floor().long().clamp(0, self.height - 1)
        return ~inside | self._occupancy[row, col]

    def _segment_blocked(self, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        frac = torch.linspace(1.0 / SEGMENT_SAMPLES, 1.0, SEGMENT_SAMPLES, device=self.device)
        points = start.unsqueeze(1) + frac.view(1, -1, 1) * (end - start).unsqueeze(1)
        return self.blocked(points).any(-1)

    def _observe(self, **extra: torch.Tensor) -> TensorDict:
        bs, w = self.batch_size, self.window
        c, s = torch.cos(self._theta), torch.sin(self._theta)
        ahead = torch.stack([c, s], -1)  # [n, 2]
        left = torch.stack([-s, c], -1)
        off = self._offsets  # [w*w, 2]
        points = (
            self._pos.unsqueeze(1)
            + off[:, 0].view(1, -1, 1) * ahead.unsqueeze(1)
            + off[:, 1].view(1, -1, 1) * left.unsqueeze(1)
        )
        window = self.blocked(points).to(torch.uint8).reshape(*bs, 1, w, w)
        delta = self._target - self._pos
        target = torch.stack([(delta * ahead).sum(-1), (delta * left).sum(-1)], -1)
        return TensorDict(
            window=window,
            target=(target / self.stage_line).reshape(*bs, 2),
            position=self._pos.reshape(*bs, 2).clone(),
            heading=self._theta.reshape(*bs, 1).clone(),
            stage=self._stage.reshape(*bs, 1).clone(),
            **extra,
            batch_size=bs,
            device=self.device,
        )

    # ------------------------------------------------------------------ start distribution
    def _sample_starts(self, pending: torch.Tensor) -> None:
        """Draws positions and headings for the ``pending`` elements (in place)."""
        k = self._start_stage or 0
        n, dev, mask = self._n, self.device, pending.clone()
        for _ in range(MAX_ATTEMPTS):
            u = torch.rand(n, 2, device=dev, generator=self.rng)
            cand = torch.stack(
                [(k + u[:, 0]) * self.stage_line, u[:, 1] * self.height], -1
            )  # uniform in stage k's half
            far = (cand - self._target).norm(dim=-1) > self.success_radius
            take = pending & far & ~self.blocked(cand)
            self._pos.copy_(torch.where(take.unsqueeze(-1), cand, self._pos))
            pending = pending & ~take
            if not pending.any():
                break
        else:
            raise RuntimeError(f"could not draw free start positions in {MAX_ATTEMPTS} attempts.")
        theta = math.pi - 2.0 * math.pi * torch.rand(n, device=dev, generator=self.rng)
        self._theta.copy_(torch.where(mask, theta, self._theta))

    # ------------------------------------------------------------------ EnvBase API
    def _flags(self) -> dict[str, torch.Tensor]:
        zeros = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return {"done": zeros, "terminated": zeros.clone(), "truncated": zeros.clone()}

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is None:
            mask = torch.ones(self._n, dtype=torch.bool, device=self.device)
        else:
            mask = reset.reshape(self._n)
        self._sample_starts(mask)
        self._stage.masked_fill_(mask, self._start_stage or 0)
        self._steps.masked_fill_(mask, 0)
        return self._observe(**self._flags())

    def _action(self, tensordict: TensorDictBase, robot: str) -> torch.Tensor:
        value = tensordict.get((robot, "action"), None)
        if value is None:
            return torch.zeros(self._n, device=self.device)
        return value.reshape(self._n).to(torch.float32)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        n, dev, gen = self._n, self.device, self.rng
        slider = self._is_slider[self._stage]
        turn = self.max_turn * self._action(tensordict, "slider").clamp(-1.0, 1.0)
        propel = self._action(tensordict, "propelled").clamp(0.0, 1.0)
        speed = self.step_length * torch.where(slider, 1.0, propel)
        heading = torch.stack([torch.cos(self._theta), torch.sin(self._theta)], -1)
        noise = self.translational_noise * torch.randn(n, 2, device=dev, generator=gen)
        cand = self._pos + speed.unsqueeze(-1) * heading + noise
        rejected = self._segment_blocked(self._pos, cand)
        self._pos.copy_(torch.where(rejected.unsqueeze(-1), self._pos, cand))
        spin = self.rotational_noise * torch.randn(n, device=dev, generator=gen)
        self._theta.copy_(wrap_angle(self._theta + torch.where(slider, turn, 0.0) + spin))
        if self.num_stages > 1:
            crossed = self._pos[:, 0] >= self.stage_line
            self._stage.copy_(torch.where(crossed, 1, self._stage))
        self._steps.add_(1)
        bs = self.batch_size
        d = (self._pos - self._target).norm(dim=-1)
        terminated = (d <= self.success_radius).reshape(*bs, 1)
        truncated = (self._steps >= self.max_steps).reshape(*bs, 1)
        return self._observe(
            reward=terminated.to(torch.float32),
            done=terminated | truncated,
            terminated=terminated,
            truncated=truncated,
        )

    def stage_observation_keys(self, stage: int) -> list[str]:
        """Network inputs of every stage: the obstacle window and the target."""
        return ["window", "target"]

    def stage_action_key(self, stage: int) -> tuple[str, str]:
        """The action entry of ``stage``'s robot, e.g. ``("slider", "action")``."""
        return (self.robots[stage], "action")

    # ------------------------------------------------------------------ state access
    def set_state(
        self,
        position: Sequence[float] | Sequence[Sequence[float]] | torch.Tensor,
        *,
        heading: float | Sequence[float] | torch.Tensor = 0.0,
        stage: int | None = None,
    ) -> TensorDictBase:
        """Puts every element in a given state, like a reset (step counters restart at 0).

        ``position`` is one ``(x, y)`` (``[1, 2]`` or ``[2]``) or one per element
        (``[*B, 2]``); ``heading`` a scalar or one per element. ``stage`` defaults to the stage
        of the position's half. Returns the matching reset-style TensorDict.
        """
        pos = torch.as_tensor(position, dtype=torch.float32, device=self.device).reshape(-1, 2)
        theta = torch.as_tensor(heading, dtype=torch.float32, device=self.device).reshape(-1)
        self._pos.copy_(pos.expand(self._n, 2))
        self._theta.copy_(wrap_angle(theta.expand(self._n)))
        if stage is None:
            right = (self._pos[:, 0] >= self.stage_line).long()
            self._stage.copy_(right.clamp(max=self.num_stages - 1))
        else:
            if not 0 <= stage < self.num_stages:
                raise ValueError(f"stage must be in [0, {self.num_stages}), got {stage}.")
            self._stage.fill_(stage)
        self._steps.zero_()
        return self._observe(**self._flags())
