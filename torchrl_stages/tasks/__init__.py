"""Task-specific reports (extra metrics and figures), looked up by ``task.name``.

A report is ``report(task, learners, run_dir, plots) -> dict`` and its dict is stored under
``"task"`` in ``eval.json``. Tasks without one get the generic whole-task evaluation only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torchrl_stages.tasks import cargo, gridworld, manipulator

Report = Callable[..., dict[str, Any]]

REPORTS: dict[str, Report] = {
    "cargo": cargo.report,
    "gridworld": gridworld.report,
    "manipulator": manipulator.report,
}
