"""Cargo transport by two robots (the paper's Fig. 3): the env and its obstacle map
(``data/cargo_map.txt``), the report and the figure."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403
from .report import report

register_task("cargo", report=report)

__all__ = env.__all__
