"""The package's tasks, installed as ``torchrl_stages.envs``: one sub-package each (its env,
report and figures; its ``__init__`` registers the task with
:func:`torchrl_stages.task_registry.register_task`), and its config ``conf/task/<task>.yaml``. Every
sub-package is imported here, so a task is its folder and its YAML, nothing else."""

import importlib
import pkgutil

from .cargo import ROBOTS, CargoEnv, load_obstacle_map
from .gridworld import (
    GridWorldEnv,
    greedy_path_from_values,
    gridworld_optimal_values,
    gridworld_shortest_steps,
    measure_throughput,
)
from .manipulator import ManipulatorEnv, forward_kinematics, inverse_kinematics, wrap_angle
from .minigrid import MiniGridEnv

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
    "MiniGridEnv",
    "forward_kinematics",
    "inverse_kinematics",
    "wrap_angle",
]

for _task in pkgutil.iter_modules(__path__):  # each task's package registers it
    if _task.ispkg:
        importlib.import_module(f"{__name__}.{_task.name}")
