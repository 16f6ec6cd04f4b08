"""Helpers shared by the multi-stage envs."""

from __future__ import annotations


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
