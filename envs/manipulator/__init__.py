"""The two-link arm (the paper's Fig. 4): coarse then fine reaching (``env``), its report of the
final distances (``report``) and its figure (``figures``). Its config is
``conf/task/manipulator.yaml``."""

from torchrl_stages.task_registry import register_task

from .env import ManipulatorEnv, forward_kinematics, inverse_kinematics, wrap_angle
from .report import report

register_task("manipulator", report=report)

__all__ = ["ManipulatorEnv", "forward_kinematics", "inverse_kinematics", "wrap_angle"]
