"""Schedules: how a task's stages are trained, one module each, registered by name
(``schedule=<name>``); every module here is imported with the package."""

import importlib
import pkgutil

from torchrl_stages.schedules.backward import BackwardSchedule, train_backward, train_stage
from torchrl_stages.schedules.base import (
    SCHEDULES,
    Probe,
    Schedule,
    StageKeeper,
    Trained,
    get_schedule,
    register_schedule,
)
from torchrl_stages.schedules.flat import train_flat
from torchrl_stages.schedules.joint import JointTrainer

for _module in pkgutil.iter_modules(__path__):  # each schedule module registers itself
    importlib.import_module(f"{__name__}.{_module.name}")

__all__ = [
    "SCHEDULES",
    "BackwardSchedule",
    "JointTrainer",
    "Probe",
    "Schedule",
    "StageKeeper",
    "Trained",
    "get_schedule",
    "register_schedule",
    "train_backward",
    "train_flat",
    "train_stage",
]
