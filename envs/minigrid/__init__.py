"""MiniGrid's multi-stage levels (DoorKey, KeyCorridor, UnlockPickup): the staged env
(``env``), the report of a run's evaluation (``report``) and its figure (``figures``). Needs the
``minigrid`` extra. Its config is ``conf/task/minigrid.yaml``."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403 (the env's public names)
from .report import report

register_task("minigrid", report=report)

__all__ = list(env.__all__)
