"""What a task adds to a run beyond its env and config, by ``task.name``: registered in the
module that defines its env (the package's own tasks: in ``torchrl_stages.envs``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TaskReport:
    """What a task adds: ``report(task, learners, evaluation, run_dir, plots) -> dict`` its
    metrics (``eval.json``'s ``"task_metrics"``) and figures; ``headline`` the metrics a sweep
    summary shows; ``probe(task, learners) -> dict`` what ``eval.probe=true`` follows."""

    report: Callable[..., dict[str, Any]] | None = None
    headline: tuple[str, ...] = ()
    probe: Callable[..., dict[str, float]] | None = None


#: registered tasks by ``task.name``
TASKS: dict[str, TaskReport] = {}


def register_task(
    name: str,
    *,
    report: Callable[..., dict[str, Any]] | None = None,
    headline: Sequence[str] = (),
    probe: Callable[..., dict[str, float]] | None = None,
) -> TaskReport:
    TASKS[name] = TaskReport(report, tuple(headline), probe)
    return TASKS[name]


def task_report(name: str) -> TaskReport | None:
    """The registered :class:`TaskReport` of ``name``, or ``None``."""
    if name not in TASKS:
        importlib.import_module("torchrl_stages.envs")  # the package's own tasks register there
    return TASKS.get(name)
