"""Cargo transport by two robots (the paper's Fig. 3): the env and its obstacle map (``env``,
``data/cargo_map.txt``), its report (``report``) and figure (``figures``). Its config is
``conf/task/cargo.yaml``."""

from torchrl_stages.task_registry import register_task

from .env import ROBOTS, CargoEnv, load_obstacle_map
from .report import report

register_task("cargo", report=report)

__all__ = ["ROBOTS", "CargoEnv", "load_obstacle_map"]
