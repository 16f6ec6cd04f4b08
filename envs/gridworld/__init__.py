"""The multi-stage grid world (the paper's Fig. 2): the env and its dynamic-programming solution
(``env``), the report that checks a run against it (``report``) and its figures (``figures``).
Its config is ``conf/task/gridworld.yaml``."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403 (the env's public names)
from .report import probe, report

register_task("gridworld", report=report, headline=["value_map_max_abs_error"], probe=probe)

__all__ = list(env.__all__)
