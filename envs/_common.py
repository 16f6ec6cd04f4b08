"""What the tasks share: the torch-native envs' mixin and start draws, episode paths, segments."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded

MAX_ATTEMPTS = 100  # draws of a start state before giving up


def check_start_stage(value: int | None, num_stages: int) -> int | None:
    """Validates a ``start_stage`` argument: ``None`` or an int in ``[0, num_stages)``."""
    if value is None:
        return None
    if isinstance(value, bool) or int(value) != value:
        raise ValueError(f"start_stage must be an int or None, got {value!r}.")
    value = int(value)
    if not 0 <= value < num_stages:
        raise ValueError(f"start_stage={value} is out of range [0, num_stages={num_stages}).")
    return value


def check_positive(**values: float) -> None:
    """Refuses a value that is not positive, naming its key."""
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}.")


def draw_until(
    draw: Callable[[], tuple[torch.Tensor, torch.Tensor]],
    current: torch.Tensor,
    pending: torch.Tensor,
    what: str,
) -> torch.Tensor:
    """``current`` with its ``pending`` rows replaced by ok draws of ``draw() -> (rows, ok)``."""
    for _ in range(MAX_ATTEMPTS):
        candidates, ok = draw()
        take = pending & ok
        current = torch.where(take.unsqueeze(-1), candidates, current)
        pending = pending & ~take
        if not pending.any():
            return current
    raise RuntimeError(f"could not draw {what} in {MAX_ATTEMPTS} attempts.")


def episode_path(rollout: TensorDictBase, key: str, i: int, steps: int) -> torch.Tensor:
    """``rollout[key]`` along row ``i``'s first episode of ``steps`` steps: ``[steps + 1, ...]``."""
    return torch.cat([rollout[key][i, :1], rollout["next", key][i, :steps]])


def stage_segments(xy: np.ndarray, stages: np.ndarray, k: int) -> list[np.ndarray]:
    """The pieces of a path ``xy [T+1, 2]`` whose steps start in stage ``k`` (``stages [T+1]``),
    each with the point where its last step ends."""
    idx = np.flatnonzero(stages[:-1] == k)
    runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
    return [xy[run[0] : run[-1] + 2] for run in runs if len(run)]


class StageStarts:
    """Mixin of the torch-native multi-stage envs: ``start_stage``, a seeded ``rng``, and the
    dynamic state in ``state_dict``.

    ``start_stage`` is the stage whose states resets are drawn from (``None``: whole-task
    starts). The buffers named in ``_dynamic_state`` (everything a step changes) and the
    generator's state travel in ``state_dict()["_extra_state"]``, so a run resumed from a
    checkpoint continues the same episodes with the same noise.
    """

    num_stages: int
    max_steps: int
    rng: torch.Generator | None = None
    _dynamic_state: tuple[str, ...] = ()

    def _init_state(self, max_steps: int, **buffers: torch.Tensor | None) -> None:
        """Sets ``max_steps``, the reward and done specs, and buffers kept out of state_dict."""
        check_positive(max_steps=max_steps)
        self.max_steps = int(max_steps)
        bs, dev = self.batch_size, self.device
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=torch.float32, device=dev)
        flag = Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(
            done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=bs
        )
        buffers["_steps"] = torch.zeros(self._n, dtype=torch.int64, device=dev)
        for name, buf in buffers.items():
            self.register_buffer(name, buf, persistent=False)

    def _reset_mask(self, tensordict: TensorDictBase | None) -> torch.Tensor:
        """Which (flattened) elements a reset restarts: its ``"_reset"`` entry, or all."""
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is None:
            return torch.ones(self._n, dtype=torch.bool, device=self.device)
        return reset.reshape(self._n)

    def _pairs(self, name: str, value: Sequence[float] | torch.Tensor, dtype: torch.dtype):
        """``value``, one pair or one per element (``[*B, 2]``), as ``[n, 2]``."""
        pairs = torch.as_tensor(value, dtype=dtype, device=self.device)
        if pairs.shape == (2,):
            return pairs.expand(self._n, 2)
        if pairs.shape == (*self.batch_size, 2):
            return pairs.reshape(self._n, 2)
        raise ValueError(
            f"{name} must be a pair or have shape {[*self.batch_size, 2]}, "
            f"got shape {list(pairs.shape)}."
        )

    def _reset_flags(self) -> dict[str, torch.Tensor]:
        zeros = torch.zeros((*self.batch_size, 1), dtype=torch.bool, device=self.device)
        return {"done": zeros, "terminated": zeros.clone(), "truncated": zeros.clone()}

    def _step_flags(self, solved: torch.Tensor) -> dict[str, torch.Tensor]:
        """Counts a step: reward 1 and ``terminated`` where ``solved``, then the time limit."""
        self._steps.add_(1)
        terminated = solved.reshape(*self.batch_size, 1)
        truncated = (self._steps >= self.max_steps).reshape(*self.batch_size, 1)
        return {
            "reward": terminated.to(torch.float32),
            "done": terminated | truncated,
            "terminated": terminated,
            "truncated": truncated,
        }

    def get_extra_state(self) -> dict:
        return {
            "rng": None if self.rng is None else self.rng.get_state(),
            **{name: getattr(self, name).clone() for name in self._dynamic_state},
        }

    def set_extra_state(self, state: dict) -> None:
        self.rng = None
        if state["rng"] is not None:
            self.rng = torch.Generator(device=self.device or "cpu")
            self.rng.set_state(state["rng"])
        for name in self._dynamic_state:
            getattr(self, name).copy_(state[name])

    @property
    def start_stage(self) -> int | None:
        return self._start_stage

    @start_stage.setter
    def start_stage(self, value: int | None) -> None:
        self._start_stage = check_start_stage(value, self.num_stages)

    def _set_seed(self, seed: int | None) -> None:
        self.rng = None
        if seed is not None:
            self.rng = torch.Generator(device=self.device or "cpu").manual_seed(int(seed))
