"""Multi-stage grid world (batched, torch-native) and its dynamic-programming solution."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import StageStarts, check_start_stage, sparse_reward_and_done_specs

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
    """Validates the grid arguments; returns the target cell (default: bottom-right corner)."""
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
    """A ``size x size`` grid split into ``num_stages`` vertical strips (stages).

    Row 0 is the top, column 0 the left. Actions (``Categorical(4)``): 0 row-1, 1 row+1,
    2 col-1, 3 col+1. A move off the grid or into an earlier stage's strip is blocked (the
    agent stays). Entering ``target`` gives reward 1 and ``terminated=True``; after
    ``max_steps`` steps an element is ``truncated`` (both flags can be set on the same step).
    The observation is ``[row, col] / 5``. Partial resets through ``"_reset"`` are supported.

    Args:
        batch_size: batch shape of the env; any shape, e.g. ``()``, ``(64,)``, ``(2, 3)``.

    Keyword Args:
        size: grid side. num_stages: number of strips (must divide ``size``).
        target: terminal cell, default ``(size - 1, size - 1)``, i.e. ``(24, 24)``.
        max_steps: per-element time limit.
        start_cell: fixed start, a pair ``(r, c)`` or one cell per element (shape ``[*B, 2]``).
        start_stage: if set, starts are uniform over stage ``k``'s strip minus the target;
            takes precedence over ``start_cell``. Default starts: column 0, uniform row.
        stage_start_rows: ``(first, end)``: stage starts (``start_stage``, and
            :meth:`start_states` of a stage) only in rows ``first..end-1`` of the strip; a
            start region that can miss where the previous stage arrives, which the handoff
            diagnostic reports (default: every row).
        device: torch device.

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

    _dynamic_state = ("_cell", "_steps")  # what a step changes (see StageStarts)

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
        self.stage_width = self.size // self.num_stages
        if max_steps <= 0:
            raise ValueError(f"max_steps must be positive, got {max_steps}.")
        self.max_steps = int(max_steps)
        bs, dev = self.batch_size, self.device
        self._n = bs.numel()
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*bs, 2), dtype=torch.float32, device=dev), shape=bs
        )
        self.action_spec = Categorical(4, shape=bs, dtype=torch.int64, device=dev)
        self.reward_spec, self.done_spec = sparse_reward_and_done_specs(bs, dev)
        # dynamics as lookup tables indexed by cell * 4 + action (cell = row * size + col)
        nxt, enters, _, _ = _transitions(self.size, self.num_stages, self.target)
        rc = np.stack(np.divmod(np.arange(self.size**2), self.size), -1)
        buffers = {  # non-persistent buffers: follow env.to(device), stay out of state_dict
            "_next_cell": torch.as_tensor(nxt.T.reshape(-1), device=dev),
            "_enters": torch.as_tensor(enters.T.reshape(-1), device=dev),
            "_cell_obs": torch.as_tensor(rc / OBS_SCALE, dtype=torch.float32, device=dev),
            "_cell": torch.zeros(self._n, dtype=torch.int64, device=dev),  # flat internal state
            "_steps": torch.zeros(self._n, dtype=torch.int64, device=dev),
            "_start_cell": None,
        }
        for name, buf in buffers.items():
            self.register_buffer(name, buf, persistent=False)
        self.rng = None
        self.start_cell = start_cell
        self.start_stage = start_stage

    # ------------------------------------------------------------------ start distribution
    @property
    def start_cell(self) -> torch.Tensor | None:
        """Fixed start cells as a ``[*B, 2]`` int64 tensor (``None`` if unset)."""
        if self._start_cell is None:
            return None
        rc = torch.stack([self._start_cell // self.size, self._start_cell % self.size], -1)
        return rc.reshape(*self.batch_size, 2)

    @start_cell.setter
    def start_cell(self, value: Sequence[int] | torch.Tensor | None) -> None:
        if value is None:
            self._start_cell = None
            return
        cells = torch.as_tensor(value, dtype=torch.int64, device=self.device)
        if cells.shape == (2,):
            cells = cells.expand(self._n, 2)
        elif cells.shape == (*self.batch_size, 2):
            cells = cells.reshape(self._n, 2)
        else:
            raise ValueError(
                f"start_cell must be a pair (r, c) or have shape {[*self.batch_size, 2]}, "
                f"got shape {list(cells.shape)}."
            )
        if ((cells < 0) | (cells >= self.size)).any():
            raise ValueError(f"start_cell has cells outside the {self.size}x{self.size} grid.")
        self._start_cell = cells[:, 0] * self.size + cells[:, 1]

    @property
    def can_step_finished(self) -> bool:
        """Whether a rollout may step a finished element on instead of resetting it, with no
        effect on anything it reads (:func:`~torchrl_stages.evaluate.rollout_first_episodes`):
        true with fixed starts (``start_cell`` and no ``start_stage``), where a reset draws
        nothing from ``rng`` and the moves are deterministic, as in the evaluation envs
        (:meth:`start_states`)."""
        return self._start_cell is not None and self._start_stage is None

    def _sample_starts(self) -> torch.Tensor:
        """Flat start cells (``row * size + col``), one per (flattened) batch element."""
        n, dev, w = self._n, self.device, self.stage_width
        if self._start_stage is not None and self.stage_start_rows is not None:
            cells = self._stage_cells(self._start_stage)
            idx = torch.randint(len(cells), (n,), device=dev, generator=self.rng)
            return cells.to(dev)[idx, 0] * self.size + cells.to(dev)[idx, 1]
        if self._start_stage is not None:
            c0 = self._start_stage * w
            tr, tc = self.target
            has_target = c0 <= tc < c0 + w
            idx = torch.randint(
                self.size * w - int(has_target), (n,), device=dev, generator=self.rng
            )
            if has_target:  # skip the target: uniform over the other cells of the strip
                idx = idx + (idx >= tr * w + (tc - c0)).long()
            return (idx // w) * self.size + c0 + idx % w
        if self._start_cell is not None:
            return self._start_cell
        return torch.randint(self.size, (n,), device=dev, generator=self.rng) * self.size

    def start_states(self, stage: int | None = None) -> dict[str, Any]:
        """Every start state of ``stage`` (``None``: the whole-task starts, column 0), as the
        constructor arguments of an env whose batch element ``i`` always starts at the ``i``-th:
        ``{"batch_size": (M,), "start_cell": cells [M, 2], "start_stage": None}``.

        Stage ``k``'s start states are all cells of its strip but the target; evaluations from
        all of them leave no state the previous stage can hand over unchecked.

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
            check_start_stage(stage, self.num_stages)
            cells = self._stage_cells(stage)
        return {"batch_size": (len(cells),), "start_cell": cells, "start_stage": None}

    def _stage_cells(self, stage: int) -> torch.Tensor:
        """The ``(row, col)`` start cells of stage ``stage``, row-major, the target left out."""
        w = self.stage_width
        first, end = self.stage_start_rows or (0, self.size)
        rows, cols = torch.meshgrid(
            torch.arange(first, end), torch.arange(stage * w, (stage + 1) * w), indexing="ij"
        )
        cells = torch.stack([rows.reshape(-1), cols.reshape(-1)], -1)
        return cells[(cells != torch.tensor(self.target)).any(-1)]

    def observation_of(self, cells: torch.Tensor) -> torch.Tensor:
        """The observation of integer cells ``[..., 2]`` (``(row, col)``), the inverse of
        :meth:`cells_of`."""
        return cells.to(torch.float32) / OBS_SCALE

    # ------------------------------------------------------------------ EnvBase API
    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        starts = self._sample_starts()
        if reset is None:
            self._cell.copy_(starts)
            self._steps.zero_()
        else:
            mask = reset.reshape(self._n)
            self._cell.copy_(torch.where(mask, starts, self._cell))
            self._steps.masked_fill_(mask, 0)
        zeros = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return TensorDict(
            observation=self._cell_obs[self._cell].reshape(*self.batch_size, 2),
            done=zeros,
            terminated=zeros.clone(),
            truncated=zeros.clone(),
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        # hot path: a handful of vectorized ops, no spec checks, state updated in place
        idx = self._cell * 4 + tensordict.get("action").reshape(self._n)
        terminated = self._enters[idx].reshape(*self.batch_size, 1)
        self._cell.copy_(self._next_cell[idx])
        self._steps.add_(1)
        truncated = (self._steps >= self.max_steps).reshape(*self.batch_size, 1)
        return TensorDict(
            observation=self._cell_obs[self._cell].reshape(*self.batch_size, 2),
            reward=terminated.to(torch.float32),
            done=terminated | truncated,
            terminated=terminated,
            truncated=truncated,
            batch_size=self.batch_size,
            device=self.device,
        )

    # ------------------------------------------------------------------ helpers
    def cells_of(self, observation: torch.Tensor) -> torch.Tensor:
        """Integer ``(row, col)`` cells, shape ``[..., 2]``, of observations ``[..., 2]``."""
        return torch.round(observation * OBS_SCALE).long()

    def stage_fn(self, tensordict: TensorDictBase | torch.Tensor) -> torch.Tensor:
        """Stage index (int64, ``[..., 1]``) of ``tensordict["observation"]``.

        Works for any leading batch shape; a raw observation tensor is accepted too.
        """
        obs = tensordict if isinstance(tensordict, torch.Tensor) else tensordict.get("observation")
        col = torch.round(obs[..., 1:2] * OBS_SCALE).long()
        return (col // self.stage_width).clamp_(0, self.num_stages - 1)


# ---------------------------------------------------------------------- dynamic programming
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


def gridworld_optimal_values(
    gammas: Sequence[float],
    *,
    size: int = 25,
    num_stages: int = 5,
    target: Sequence[int] | None = None,
    tol: float = 1e-12,
    max_iter: int = 100_000,
) -> np.ndarray:
    """Optimal values ``(size, size)`` (float64, row 0 on top) by value iteration.

    ``V(s) = max_a [r(s, a) + gammas[stage(s)] * (0 if s' is the target else V(s'))]`` and
    ``V(target) = 0``: the merged stage-wise value function (Proposition 1 of the paper).
    ``target`` defaults to ``(size - 1, size - 1)``.
    """
    tgt = _check_grid(size, num_stages, target)
    g = np.asarray(gammas, dtype=np.float64)
    if g.shape != (num_stages,):
        raise ValueError(f"gammas must have num_stages={num_stages} entries, got {len(g)}.")
    nxt, enters, stage, t = _transitions(size, num_stages, tgt)
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
    """Greedy path (visited cells, start included) following ``argmax_a r + gamma * V(s')``.

    Stops at the target or after ``max_steps`` moves; ties go to the lowest action index.
    ``gammas`` defaults to 0.99 in every stage; ``target`` to ``(size - 1, size - 1)``.
    """
    values = np.asarray(values, dtype=np.float64)
    size = values.shape[0]
    tgt = _check_grid(size, num_stages, target)
    g = np.full(num_stages, 0.99) if gammas is None else np.asarray(gammas, dtype=np.float64)
    if g.shape != (num_stages,):
        raise ValueError(f"gammas must have num_stages={num_stages} entries, got {len(g)}.")
    nxt, enters, stage, t = _transitions(size, num_stages, tgt)
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
    """Fewest moves from ``start`` to the target (breadth-first search over the grid's moves,
    blocked ones included); ``None`` when the target cannot be reached.

    Examples:
        >>> gridworld_shortest_steps((0, 0))
        48
    """
    tgt = _check_grid(size, num_stages, target)
    nxt, _, _, t = _transitions(size, num_stages, tgt)
    s = int(start[0]) * size + int(start[1])
    dist = {s: 0}
    frontier = [s]
    while frontier:
        if t in dist:
            return dist[t]
        nxt_frontier = []
        for cell in frontier:
            for c in nxt[:, cell].tolist():
                if c not in dist:
                    dist[c] = dist[cell] + 1
                    nxt_frontier.append(c)
        frontier = nxt_frontier
    return dist.get(t)


def measure_throughput(batch_size: int, steps: int = 200, seed: int = 0) -> float:
    """Frames per second of ``step_and_maybe_reset`` with uniformly random actions."""
    env = GridWorldEnv((batch_size,))
    env.set_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    actions = torch.randint(4, (steps + 5, batch_size), generator=gen)
    td = env.reset()
    for i in range(5):  # warm-up (allocations, cached spec lookups)
        td["action"] = actions[i]
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for i in range(5, steps + 5):
        td["action"] = actions[i]
        _, td = env.step_and_maybe_reset(td)
    return steps * batch_size / (time.perf_counter() - start)
