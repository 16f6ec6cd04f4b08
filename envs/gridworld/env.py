"""The multi-stage grid world (batched, torch-native) and its dynamic-programming solution."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import StageStarts, check_start_stage

__all__ = [
    "GridWorldEnv",
    "greedy_path_from_values",
    "gridworld_optimal_values",
    "gridworld_shortest_steps",
    "measure_throughput",
]

OBS_SCALE = 5.0  # observation = cell / 5, as in the paper's reference code (independent of size)
# action -> (d_row, d_col): 0 up (row-1), 1 down (row+1), 2 left (col-1), 3 right (col+1)
MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))


def _check_grid(size: int, num_stages: int, target: Sequence[int] | None) -> tuple[int, int]:
    """The target cell (default: the bottom-right one) of a valid grid."""
    if size <= 0 or num_stages <= 0 or size % num_stages:
        raise ValueError(f"size ({size}) must be a positive multiple of num_stages ({num_stages}).")
    if target is None:
        return size - 1, size - 1
    tr, tc = (int(v) for v in target)
    if not (0 <= tr < size and 0 <= tc < size):
        raise ValueError(f"target {tuple(target)} is outside the {size}x{size} grid.")
    return tr, tc


def _check_rows(size: int, rows: Sequence[int] | None) -> tuple[int, int] | None:
    if rows is None:
        return None
    first, end = (int(r) for r in rows)
    if not 0 <= first < end <= size:
        raise ValueError(f"stage_start_rows must be (first, end) with 0 <= first < end <= {size}.")
    return first, end


class GridWorldEnv(StageStarts, EnvBase):
    """A ``size x size`` grid split into ``num_stages`` vertical strips, one per stage.

    Row 0 is the top, column 0 the left. Actions (``Categorical(4)``): 0 row-1, 1 row+1,
    2 col-1, 3 col+1; a move off the grid or into an earlier stage's strip is blocked. Entering
    ``target`` (default: the bottom-right cell) gives reward 1 and ``terminated``; after
    ``max_steps`` steps an element is ``truncated``. The observation is ``[row, col] / 5``.
    Starts: ``start_stage`` (uniform over stage k's strip minus the target, limited to rows
    ``stage_start_rows = (first, end)`` when given), else ``start_cell`` (a pair or one per
    element, ``[*B, 2]``), else column 0 with a uniform row.

    Examples:
        >>> import torch
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> env = GridWorldEnv((4,), start_cell=(23, 24))
        >>> td = env.reset()
        >>> td["action"] = torch.ones(4, dtype=torch.int64)  # move down into the target
        >>> td = env.step(td)
        >>> td["next", "reward"].squeeze(-1).tolist(), td["next", "terminated"].all().item()
        ([1.0, 1.0, 1.0, 1.0], True)
        >>> env.stage_fn(td["next"]).squeeze(-1).tolist()
        [4, 4, 4, 4]
    """

    _dynamic_state = ("_cell", "_steps")

    def __init__(
        self,
        batch_size: Sequence[int] | torch.Size = (),
        *,
        size: int = 25,
        num_stages: int = 5,
        target: Sequence[int] | None = None,
        max_steps: int = 200,
        start_cell: Sequence[int] | torch.Tensor | None = None,
        start_stage: int | None = None,
        stage_start_rows: Sequence[int] | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.size, self.num_stages = int(size), int(num_stages)
        self.stage_start_rows = _check_rows(self.size, stage_start_rows)
        self.target = _check_grid(self.size, self.num_stages, target)
        self.stage_width = w = self.size // self.num_stages
        first, end = self.stage_start_rows or (0, self.size)
        self._stage_starts = []  # each stage's start cells, row-major, the target left out
        for k in range(self.num_stages):
            rows, cols = torch.meshgrid(
                torch.arange(first, end), torch.arange(k * w, (k + 1) * w), indexing="ij"
            )
            cells = torch.stack([rows.reshape(-1), cols.reshape(-1)], -1)
            self._stage_starts.append(cells[(cells != torch.tensor(self.target)).any(-1)])
        bs, dev = self.batch_size, self.device
        self._n = bs.numel()
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, 2), dtype=torch.float32, device=dev), shape=bs
        )
        self.action_spec = Categorical(4, shape=bs, dtype=torch.int64, device=dev)
        # the dynamics as lookup tables indexed by cell * 4 + action (cell = row * size + col)
        nxt, enters, _, _ = _transitions(self.size, self.num_stages, self.target)
        rc = np.stack(np.divmod(np.arange(self.size**2), self.size), -1)
        self._init_state(
            max_steps,
            _next_cell=torch.as_tensor(nxt.T.reshape(-1), device=dev),
            _enters=torch.as_tensor(enters.T.reshape(-1), device=dev),
            _cell_obs=torch.as_tensor(rc / OBS_SCALE, dtype=torch.float32, device=dev),
            _cell=torch.zeros(self._n, dtype=torch.int64, device=dev),
            _start_cell=None,
        )
        self.start_cell = start_cell
        self.start_stage = start_stage

    @property
    def start_cell(self) -> torch.Tensor | None:
        """The fixed start cells, int64 ``[*B, 2]``, or ``None``."""
        if self._start_cell is None:
            return None
        rc = torch.stack([self._start_cell // self.size, self._start_cell % self.size], -1)
        return rc.reshape(*self.batch_size, 2)

    @start_cell.setter
    def start_cell(self, value: Sequence[int] | torch.Tensor | None) -> None:
        if value is None:
            self._start_cell = None
            return
        cells = self._pairs("start_cell", value, torch.int64)
        if ((cells < 0) | (cells >= self.size)).any():
            raise ValueError(f"start_cell has cells outside the {self.size}x{self.size} grid.")
        self._start_cell = cells[:, 0] * self.size + cells[:, 1]

    @property
    def can_step_finished(self) -> bool:
        """Whether a rollout may step a finished element on instead of resetting it
        (:func:`~torchrl_stages.evaluate.rollout_first_episodes`): with fixed starts, a reset
        draws nothing and the moves are deterministic."""
        return self._start_cell is not None and self._start_stage is None

    def _sample_starts(self) -> torch.Tensor:
        """Flat start cells (``row * size + col``), one per element."""
        n, dev = self._n, self.device
        if self._start_stage is not None:
            cells = self._stage_starts[self._start_stage].to(dev)
            idx = torch.randint(len(cells), (n,), device=dev, generator=self.rng)
            return cells[idx, 0] * self.size + cells[idx, 1]
        if self._start_cell is not None:
            return self._start_cell
        return torch.randint(self.size, (n,), device=dev, generator=self.rng) * self.size

    def start_states(self, stage: int | None = None) -> dict[str, Any]:
        """Every start state of ``stage`` (``None``: column 0), as the arguments of an env whose
        element ``i`` always starts at the ``i``-th; a stage's are its strip but the target.

        Examples:
            >>> from torchrl_stages.envs import GridWorldEnv
            >>> env = GridWorldEnv(size=10, num_stages=2)
            >>> env.start_states(1)["batch_size"], env.start_states()["start_cell"][:2].tolist()
            ((49,), [[0, 0], [1, 0]])
        """
        if stage is None:
            rows = torch.arange(self.size)
            cells = torch.stack([rows, torch.zeros_like(rows)], -1)
            cells = cells[(cells != torch.tensor(self.target)).any(-1)]
        else:
            cells = self._stage_starts[check_start_stage(stage, self.num_stages)]
        return {"batch_size": (len(cells),), "start_cell": cells, "start_stage": None}

    def observation_of(self, cells: torch.Tensor) -> torch.Tensor:
        """The observation of cells ``[..., 2]``, the inverse of :meth:`cells_of`."""
        return cells.to(torch.float32) / OBS_SCALE

    def cells_of(self, observation: torch.Tensor) -> torch.Tensor:
        """The ``(row, col)`` cells, int64 ``[..., 2]``, of observations ``[..., 2]``."""
        return torch.round(observation * OBS_SCALE).long()

    def _observe(self, **flags: torch.Tensor) -> TensorDict:
        observation = self._cell_obs[self._cell].reshape(*self.batch_size, 2)
        return TensorDict(
            observation=observation, **flags, batch_size=self.batch_size, device=self.device
        )

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = self._reset_mask(tensordict)
        self._cell.copy_(torch.where(mask, self._sample_starts(), self._cell))
        self._steps.masked_fill_(mask, 0)
        return self._observe(**self._reset_flags())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        idx = self._cell * 4 + tensordict.get("action").reshape(self._n)
        self._cell.copy_(self._next_cell[idx])
        return self._observe(**self._step_flags(self._enters[idx]))

    def stage_fn(self, tensordict: TensorDictBase | torch.Tensor) -> torch.Tensor:
        """Stage (int64 ``[..., 1]``) of ``tensordict["observation"]`` or of an observation."""
        obs = tensordict if isinstance(tensordict, torch.Tensor) else tensordict.get("observation")
        col = torch.round(obs[..., 1:2] * OBS_SCALE).long()
        return (col // self.stage_width).clamp_(0, self.num_stages - 1)


def _transitions(
    size: int, num_stages: int, target: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Next cell ``[4, S]``, entering-target flag ``[4, S]``, stage ``[S]``, target index."""
    w = size // num_stages
    rows, cols = np.divmod(np.arange(size * size), size)
    nxt = np.empty((4, size * size), dtype=np.int64)
    for a, (dr, dc) in enumerate(MOVES):
        r, c = rows + dr, cols + dc
        ok = (r >= 0) & (r < size) & (c >= 0) & (c < size) & (np.floor_divide(c, w) >= cols // w)
        nxt[a] = np.where(ok, r * size + c, rows * size + cols)
    t = target[0] * size + target[1]
    enters = (nxt == t) & (np.arange(size * size) != t)
    return nxt, enters, cols // w, t


def _check_gammas(gammas: Sequence[float], num_stages: int) -> np.ndarray:
    g = np.asarray(gammas, dtype=np.float64)
    if g.shape != (num_stages,):
        raise ValueError(f"gammas must have num_stages={num_stages} entries, got {len(g)}.")
    return g


def gridworld_optimal_values(
    gammas: Sequence[float],
    *,
    size: int = 25,
    num_stages: int = 5,
    target: Sequence[int] | None = None,
    tol: float = 1e-12,
    max_iter: int = 100_000,
) -> np.ndarray:
    """Optimal values ``(size, size)`` (float64, row 0 on top) by value iteration: the merged
    stage-wise value function of Proposition 1, ``V(target) = 0``."""
    g = _check_gammas(gammas, num_stages)
    nxt, enters, stage, t = _transitions(size, num_stages, _check_grid(size, num_stages, target))
    reward = enters.astype(np.float64)
    disc = g[stage]
    values = np.zeros(size * size)
    for _ in range(max_iter):
        cont = np.where(nxt == t, 0.0, values[nxt])
        new = (reward + disc * cont).max(0)
        new[t] = 0.0
        delta = np.abs(new - values).max()
        values = new
        if delta < tol:
            break
    return values.reshape(size, size)


def greedy_path_from_values(
    values: np.ndarray,
    start: tuple[int, int],
    *,
    num_stages: int = 5,
    target: Sequence[int] | None = None,
    max_steps: int = 200,
    gammas: Sequence[float] | None = None,
) -> list[tuple[int, int]]:
    """The cells (start included) of the greedy path on ``values`` until the target or
    ``max_steps`` moves; ties go to the lowest action. ``gammas`` default to 0.99."""
    values = np.asarray(values, dtype=np.float64)
    size = values.shape[0]
    g = _check_gammas([0.99] * num_stages if gammas is None else gammas, num_stages)
    nxt, enters, stage, t = _transitions(size, num_stages, _check_grid(size, num_stages, target))
    flat = values.reshape(-1)
    s = int(start[0]) * size + int(start[1])
    path = [(s // size, s % size)]
    for _ in range(max_steps):
        if s == t:
            break
        cand = nxt[:, s]
        q = enters[:, s] + g[stage[s]] * np.where(cand == t, 0.0, flat[cand])
        s = int(cand[int(np.argmax(q))])
        path.append((s // size, s % size))
    return path


def gridworld_shortest_steps(
    start: Sequence[int],
    *,
    size: int = 25,
    num_stages: int = 5,
    target: Sequence[int] | None = None,
) -> int | None:
    """Fewest moves from ``start`` to the target (``None``: unreachable), by breadth-first search.

    Examples:
        >>> gridworld_shortest_steps((0, 0))
        48
    """
    nxt, _, _, t = _transitions(size, num_stages, _check_grid(size, num_stages, target))
    s = int(start[0]) * size + int(start[1])
    dist = {s: 0}
    queue = deque([s])
    while queue:
        cell = queue.popleft()
        if cell == t:
            return dist[t]
        for c in nxt[:, cell].tolist():
            if c not in dist:
                dist[c] = dist[cell] + 1
                queue.append(c)
    return None


def measure_throughput(batch_size: int, steps: int = 200, seed: int = 0) -> float:
    """Frames per second of ``step_and_maybe_reset`` with uniformly random actions."""
    env = GridWorldEnv((batch_size,))
    env.set_seed(seed)
    actions = torch.randint(
        4, (steps + 5, batch_size), generator=torch.Generator().manual_seed(seed)
    )
    td = env.reset()
    for i in range(steps + 5):
        if i == 5:  # after the warm-up (allocations, cached spec lookups)
            start = time.perf_counter()
        td["action"] = actions[i]
        _, td = env.step_and_maybe_reset(td)
    return steps * batch_size / (time.perf_counter() - start)
