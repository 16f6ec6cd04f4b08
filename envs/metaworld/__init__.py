"""Meta-World's manipulation tasks (v3; the ``metaworld`` extra) in two stages, grasp and place:
the staged env. Meta-World is imported when an env is built: the package loads without it."""

from torchrl_stages.task_registry import register_task

from . import env
from .env import *  # noqa: F403

register_task("metaworld")

__all__ = env.__all__
