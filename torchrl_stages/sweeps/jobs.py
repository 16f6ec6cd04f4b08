"""The job directories of a sweep, whatever launched them, read as data."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

#: the numbers every finished run has (``eval.json``); a task adds its headline metrics
METRICS = ("success_rate", "mean_return", "mean_steps")
#: files that make a directory a job directory
JOB_MARKERS = (".hydra/overrides.yaml", "eval.json", "status.json", "config.yaml")
SEED = re.compile(r"^\+{0,2}seed=(?P<seed>.*)$")


@dataclass
class Job:
    """One job directory of a sweep (:func:`read_job`).

    Examples:
        >>> from pathlib import Path
        >>> job = Job(Path("sweep/3"), "3", ["task.stages.s0.lr=1e-3", "seed=1"], 1, "done")
        >>> job.config, job.row()["overrides"]
        ('task.stages.s0.lr=1e-3', 'task.stages.s0.lr=1e-3 seed=1')
    """

    path: Path
    name: str  # its path relative to the sweep directory
    overrides: list[str]
    seed: int | None
    status: str  # done | incomplete | the status of status.json (failed, pruned, ...)
    reason: str | None = None
    metrics: dict[str, float | None] = field(default_factory=dict)
    train_seconds: float | None = None
    frames: int | None = None
    updates: int | None = None

    @property
    def config(self) -> str:
        """The job's configuration: its overrides without ``seed`` (``(defaults)``: none)."""
        rest = [o for o in self.overrides if SEED.match(o) is None]
        return " ".join(rest) if rest else "(defaults)"

    def row(self, metrics: Iterable[str] = METRICS) -> dict[str, Any]:
        """The job's ``summary.csv`` row."""
        return {
            "job": self.name,
            "config": self.config,
            "seed": self.seed,
            "overrides": " ".join(self.overrides),
            "status": self.status,
            "reason": self.reason,
            **{m: self.metrics.get(m) for m in metrics},
            "train_seconds": self.train_seconds,
            "frames": self.frames,
            "updates": self.updates,
        }


def configs(jobs: Iterable[Job]) -> list[str]:
    """The configurations of ``jobs`` in the order they first appear."""
    return list(dict.fromkeys(job.config for job in jobs))


def result_metrics(jobs: Iterable[Job]) -> list[str]:
    """:data:`METRICS`, then every headline metric some job reports, in the order seen."""
    return list(dict.fromkeys([*METRICS, *(m for job in jobs for m in job.metrics)]))


def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _is_job(path: Path) -> bool:
    return any((path / marker).is_file() for marker in JOB_MARKERS)


def find_jobs(sweep_dir: str | Path) -> list[Path]:
    """The job directories under ``sweep_dir`` (not in hidden folders or in a job) in natural
    order; ``sweep_dir`` itself when it holds no job below it."""
    root = Path(sweep_dir)
    jobs: list[Path] = []
    for current, dirs, _files in os.walk(root):
        here = Path(current)
        if here != root and _is_job(here):
            jobs.append(here)
            dirs[:] = []
            continue
        dirs[:] = [d for d in dirs if not d.startswith(".")]
    if not jobs and _is_job(root):
        jobs = [root]
    return sorted(jobs, key=lambda p: _natural_key(p.relative_to(root).as_posix()))


def _read(path: Path, load: Callable[[str], Any] = yaml.safe_load) -> Any:
    """What ``path`` holds; ``None`` when it is missing or damaged."""
    with contextlib.suppress(OSError, ValueError, yaml.YAMLError):
        return load(path.read_text())
    return None


def finite_float(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def _read_seed(path: Path, overrides: list[str]) -> int | None:
    for override in overrides:
        if match := SEED.match(override):
            with contextlib.suppress(ValueError):
                return int(match["seed"])
            return None
    for name in ("config.yaml", ".hydra/config.yaml"):
        saved = _read(path / name)
        if isinstance(saved, dict) and isinstance(saved.get("seed"), int):
            return saved["seed"]
    return None


def read_job(path: str | Path, sweep_dir: str | Path | None = None) -> Job:
    """One job directory: ``done`` (its ``eval.json``), the status of a newer ``status.json``,
    or ``incomplete``."""
    path = Path(path)
    root = Path(sweep_dir) if sweep_dir is not None else path.parent
    name = path.relative_to(root).as_posix() if path != root else "."
    overrides = _read(path / ".hydra" / "overrides.yaml")
    overrides = [str(o) for o in overrides] if isinstance(overrides, list) else []
    job = Job(path, name, overrides, _read_seed(path, overrides), "incomplete")
    eval_file, status_file = path / "eval.json", path / "status.json"
    result, status = _read(eval_file, json.loads), _read(status_file, json.loads)
    result = result if isinstance(result, dict) else None
    if isinstance(status, dict) and (
        result is None or status_file.stat().st_mtime > eval_file.stat().st_mtime
    ):
        job.status = str(status.get("status") or "failed")
        job.reason = None if status.get("reason") is None else str(status["reason"])
        return job
    if result is None:
        killed = "no eval.json nor status.json (still running, or killed)"
        job.reason = "eval.json is damaged" if eval_file.is_file() else killed
        return job
    job.status = "done"
    job.metrics = {m: finite_float(result.get(m)) for m in METRICS}
    task_metrics = result.get("task_metrics")
    headline = result.get("headline_metrics")
    if isinstance(task_metrics, dict) and isinstance(headline, list):
        job.metrics.update({str(m): finite_float(task_metrics.get(m)) for m in headline})
    training = result.get("training") if isinstance(result.get("training"), dict) else {}
    job.train_seconds = finite_float(training.get("seconds"))
    stages = training.get("stages") if isinstance(training.get("stages"), list) else []
    stages = [s for s in stages if isinstance(s, dict)]
    if stages:
        job.frames = int(sum(finite_float(s.get("frames")) or 0 for s in stages))
        job.updates = int(sum(finite_float(s.get("updates")) or 0 for s in stages))
    return job
