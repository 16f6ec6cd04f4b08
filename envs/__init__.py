"""Environments for torchrl-stages."""

from .cargo import ROBOTS, CargoEnv, load_obstacle_map
from .gridworld import (
    GridWorldEnv,
    greedy_path_from_values,
    gridworld_optimal_values,
    gridworld_shortest_steps,
    measure_throughput,
)
from .manipulator import ManipulatorEnv, forward_kinematics, inverse_kinematics, wrap_angle

__all__ = [
    "CargoEnv",
    "ROBOTS",
    "load_obstacle_map",
    "GridWorldEnv",
    "greedy_path_from_values",
    "gridworld_optimal_values",
    "gridworld_shortest_steps",
    "measure_throughput",
    "ManipulatorEnv",
    "forward_kinematics",
    "inverse_kinematics",
    "wrap_angle",
]
