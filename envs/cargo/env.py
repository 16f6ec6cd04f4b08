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

from .._common import StageStarts, check_positive, draw_until
from ..manipulator.env import wrap_angle

__all__ = ["CargoEnv", "ROBOTS", "load_obstacle_map"]

#: robot kinds and what their action entry ``(kind, "action")`` is
ROBOTS = ("slider", "propelled")
SEGMENT_SAMPLES = 16  # points checked along each move (spacing < 0.25 cell for moves < 4 a)


def load_obstacle_map(path: str | Path | None = None) -> torch.Tensor:
    """An obstacle map, bool ``[H, W]`` indexed ``[y, x]``; ``None``: the shipped map.

    The text has one line per row, top row (largest ``y``) first: ``#`` an obstacle cell, ``.``
    a free one; lines starting with ``;`` are comments.

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

    Positions are continuous, in robot radii (one map cell each). ``robots[0]`` drives the
    cargo left of the line ``x = W / 2`` (stage 0), ``robots[1]`` once it has crossed it (stage
    1, for good): the ``"slider"`` moves ahead and turns by ``max_turn * a``, the
    ``"propelled"`` robot moves ahead when ``a = 1``; both with Gaussian noise. A move that
    touches an obstacle or leaves the map is rejected. Within ``success_radius`` of ``target``:
    reward 1 and ``terminated``. The networks read ``"window"`` (the map around the robot,
    heading up) and ``"target"`` (in the robot's frame). ``docs/tasks/cargo.md`` has the details.

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

    stage_fn = None  # the env writes "stage": StageTransform(None, n) reads it
    _dynamic_state = ("_pos", "_theta", "_stage", "_steps")

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
        check_positive(
            success_radius=success_radius, step_length=step_length, max_turn=max_turn, window=window
        )
        if translational_noise < 0 or rotational_noise < 0:
            raise ValueError("translational_noise and rotational_noise must be >= 0.")
        self.success_radius, self.step_length = float(success_radius), float(step_length)
        self.translational_noise = float(translational_noise)
        self.rotational_noise = float(rotational_noise)
        self.max_turn, self.window = float(max_turn), int(window)
        bs, dev, f32, w = self.batch_size, self.device, torch.float32, self.window
        self._n = n = bs.numel()
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
        centers = (w - 1) / 2.0 - torch.arange(w, dtype=f32)
        ahead, left = torch.meshgrid(centers, centers, indexing="ij")  # row i ahead, column j left
        self._init_state(
            max_steps,
            _occupancy=occupancy.to(dev),
            _offsets=torch.stack([ahead, left], -1).reshape(-1, 2).to(dev),  # [w*w, 2]
            _target=torch.tensor(self.target, dtype=f32, device=dev),
            _is_slider=torch.tensor([r == "slider" for r in self.robots], device=dev),
            _pos=torch.zeros(n, 2, dtype=f32, device=dev),
            _theta=torch.zeros(n, dtype=f32, device=dev),
            _stage=torch.zeros(n, dtype=torch.int64, device=dev),
        )
        if self.blocked(self._target.unsqueeze(0)).item():
            raise ValueError(f"target {self.target} lies on an obstacle or off the map.")
        self.start_stage = start_stage

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

    def _sample_starts(self, pending: torch.Tensor) -> None:
        """Draws positions and headings for the ``pending`` elements."""
        k = self._start_stage or 0

        def draw() -> tuple[torch.Tensor, torch.Tensor]:
            u = torch.rand(self._n, 2, device=self.device, generator=self.rng)
            cand = torch.stack([(k + u[:, 0]) * self.stage_line, u[:, 1] * self.height], -1)
            far = (cand - self._target).norm(dim=-1) > self.success_radius
            return cand, far & ~self.blocked(cand)

        self._pos.copy_(draw_until(draw, self._pos, pending, "free start positions"))
        theta = math.pi - 2.0 * math.pi * torch.rand(
            self._n, device=self.device, generator=self.rng
        )
        self._theta.copy_(torch.where(pending, theta, self._theta))

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = self._reset_mask(tensordict)
        self._sample_starts(mask)
        self._stage.masked_fill_(mask, self._start_stage or 0)
        self._steps.masked_fill_(mask, 0)
        return self._observe(**self._reset_flags())

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
        solved = (self._pos - self._target).norm(dim=-1) <= self.success_radius
        return self._observe(**self._step_flags(solved))

    def stage_observation_keys(self, stage: int) -> list[str]:
        """Network inputs of every stage: the obstacle window and the target."""
        return ["window", "target"]

    def stage_action_key(self, stage: int) -> tuple[str, str]:
        """The action entry of ``stage``'s robot, e.g. ``("slider", "action")``."""
        return (self.robots[stage], "action")

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
        return self._observe(**self._reset_flags())
