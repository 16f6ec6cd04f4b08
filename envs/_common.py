"""Helpers shared by the multi-stage envs."""

from __future__ import annotations

import torch
from torchrl.data import Categorical, Composite, Unbounded


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


def sparse_reward_and_done_specs(
    batch_size: torch.Size, device: torch.device | None
) -> tuple[Unbounded, Composite]:
    """The reward spec (float ``[*B, 1]``) and the ``done``/``terminated``/``truncated`` flags
    (bool ``[*B, 1]``) shared by the multi-stage envs."""
    reward = Unbounded(shape=(*batch_size, 1), dtype=torch.float32, device=device)
    flag = Categorical(2, shape=(*batch_size, 1), dtype=torch.bool, device=device)
    done = Composite(
        done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=batch_size
    )
    return reward, done


class StageStarts:
    """Mixin of the multi-stage envs: a validated ``start_stage``, a seeded generator, and the
    env's dynamic state in ``state_dict``.

    ``start_stage`` is the stage whose states resets are drawn from (``None``: whole-task
    starts); the backward schedule sets it to train one stage. ``env.set_seed`` seeds ``rng``.
    The buffers named in ``_dynamic_state`` (positions, step counters: everything a step
    changes) and the generator's state travel in ``state_dict()["_extra_state"]``, so a run
    resumed from a checkpoint continues the same episodes with the same noise.
    """

    num_stages: int
    rng: torch.Generator | None = None
    _dynamic_state: tuple[str, ...] = ()

    def get_extra_state(self) -> dict:
        return {
            "rng": None if self.rng is None else self.rng.get_state(),
            **{name: getattr(self, name).clone() for name in self._dynamic_state},
        }

    def set_extra_state(self, state: dict) -> None:
        if state["rng"] is None:
            self.rng = None
        else:
            if self.rng is None:
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
        if seed is None:
            self.rng = None
            return
        self.rng = torch.Generator(device=self.device or "cpu").manual_seed(int(seed))
