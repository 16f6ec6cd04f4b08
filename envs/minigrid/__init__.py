"""MiniGrid's levels with a locked door (DoorKey, KeyCorridor, UnlockPickup, LockedRoom,
ObstructedMaze-1D*, ...; the ``minigrid`` extra): the staged env, the report of a run's
evaluation and the figure."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403
from .report import report

register_task("minigrid", report=report)

__all__ = env.__all__
