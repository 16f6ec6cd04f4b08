"""The multi-stage grid world (the paper's Fig. 2): the env and its dynamic-programming solution,
the report that checks a run against it, and the figures."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403
from .report import probe, report

register_task("gridworld", report=report, headline=["value_map_max_abs_error"], probe=probe)

__all__ = env.__all__
