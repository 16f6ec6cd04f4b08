"""The registry of tasks: what a task adds to a run beyond its env and config.

A task registers itself with :func:`register_task` (the package's own do so in
``torchrl_stages.envs.<task>``; a task of your own in the module that defines its env, which
Hydra imports when it builds the env). Its :class:`TaskReport` is looked up by ``task.name``:

* ``report(task, learners, evaluation, run_dir, plots) -> dict`` reads the run's whole-task
  evaluation (or runs task-specific deterministic checks), draws the task's figures, and its
  dict is stored under ``"task_metrics"`` in ``eval.json``;
* ``headline``: the names among those metrics that a sweep summary shows beside the success
  rate (listed in ``eval.json`` as ``"headline_metrics"``);
* ``probe(task, learners) -> dict``: numbers followed during training with ``eval.probe=true``.

Every run gets one whole-task evaluation
(:func:`~torchrl_stages.runs.evaluation.evaluate_run`): its success rate, returns and steps are
the run's numbers.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["TASKS", "TaskReport", "register_task", "task_report"]


@dataclass(frozen=True)
class TaskReport:
    """What a task adds to the whole-task evaluation: its report (metrics and figures), the
    names of its headline metrics, and its probe (numbers followed during training).

    Examples:
        >>> info = TaskReport(report=lambda task, learners, evaluation, run_dir, plots: {})
        >>> info.headline, info.probe
        ((), None)
    """

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
    """Registers what the task ``name`` (its ``task.name``) adds to a run; returns it.

    Examples:
        >>> def report(task, learners, evaluation, run_dir, plots):
        ...     return {"distance": 0.5}
        >>> info = register_task("my_task", report=report, headline=["distance"])
        >>> task_report("my_task") is info
        True
        >>> _ = TASKS.pop("my_task")
    """
    TASKS[name] = TaskReport(report, tuple(headline), probe)
    return TASKS[name]


def task_report(name: str) -> TaskReport | None:
    """The registered :class:`TaskReport` of ``name``, or ``None`` (a task without a report:
    its run has the whole-task numbers only)."""
    if name not in TASKS:
        importlib.import_module("torchrl_stages.envs")  # the package's own tasks register there
    return TASKS.get(name)
