"""Environments for torchrl-stages."""

from .gridworld import (
    GridWorldEnv,
    greedy_path_from_values,
    gridworld_optimal_values,
    measure_throughput,
)

__all__ = [
    "GridWorldEnv",
    "greedy_path_from_values",
    "gridworld_optimal_values",
    "measure_throughput",
]
