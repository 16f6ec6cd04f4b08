"""Helpers shared by the multi-stage envs."""

from __future__ import annotations

import torch


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


class StageStarts:
    """Mixin of the multi-stage envs: a validated ``start_stage`` and a seeded generator.

    ``start_stage`` is the stage whose states resets are drawn from (``None``: whole-task
    starts); the backward schedule sets it to train one stage. ``env.set_seed`` seeds ``rng``.
    """

    num_stages: int
    rng: torch.Generator | None = None

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
