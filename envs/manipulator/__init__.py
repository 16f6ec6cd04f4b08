"""The two-link arm (the paper's Fig. 4): coarse then fine reaching, the report of the final
distances and the figure."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403
from .report import report

register_task("manipulator", report=report)

__all__ = env.__all__
