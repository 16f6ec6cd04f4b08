"""Sweep summaries: one table, statistics across seeds and figures for a directory of runs.

A sweep directory holds one directory per job, whatever made it (Hydra's basic, joblib,
submitit or Ray launcher, the Optuna sweeper, or runs copied together by hand): each has
``.hydra/overrides.yaml`` (the job's command-line overrides), ``eval.json`` (a finished run) or
``status.json`` (a failed one) and ``metrics.csv``. :func:`summarize_sweep` only reads those
files and writes, into the sweep directory:

* ``summary.csv``: one row per job (its overrides, status and failure reason, whole-task success
  rate, mean return and steps, the value error where the task reports one, training seconds,
  frames and gradient updates);
* ``summary_configs.csv`` and ``summary.md``: per configuration (the overrides without
  ``seed``), across seeds, the mean, the interquartile mean and a bootstrap 95% confidence
  interval of the mean of each metric (plain numpy, seeded: the same files give the same
  numbers);
* ``summary_curves.png`` (learning curves per configuration: the mean over seeds and a band from
  the lowest to the highest seed) and ``summary_final.png`` (the final metrics per
  configuration: each seed, the mean and its confidence interval).

``stages-train -m`` writes them when a sweep ends (:class:`torchrl_stages.cli.SweepSummaryCallback`,
configured in ``hydra.callbacks``), ``stages-report DIR`` on demand.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import warnings
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

__all__ = [
    "Aggregate",
    "Job",
    "SweepSummary",
    "aggregate_jobs",
    "bootstrap_ci",
    "find_jobs",
    "interquartile_mean",
    "plot_sweep_curves",
    "plot_sweep_final",
    "read_job",
    "summarize_sweep",
]

SUMMARY_CSV = "summary.csv"
CONFIGS_CSV = "summary_configs.csv"
SUMMARY_MD = "summary.md"
CURVES_PNG = "summary_curves.png"
FINAL_PNG = "summary_final.png"
#: per-job numbers, from eval.json (value_error: the task's value_map_max_abs_error, if any)
METRICS = ("success_rate", "mean_return", "mean_steps", "value_error")
COLUMNS = (
    "job",
    "config",
    "seed",
    "overrides",
    "status",
    "reason",
    *METRICS,
    "train_seconds",
    "frames",
    "updates",
)
#: files that make a directory a job directory
_JOB_MARKERS = (".hydra/overrides.yaml", "eval.json", "status.json", "config.yaml")
#: learning curves of the summary: whole-task probe, stage and joint-phase evaluations
_CURVE = re.compile(
    r"^eval/(?P<scope>task|stage_(?P<stage>\d+)|joint_(?P<phase>\d+))/success_rate$"
)
_SEED = re.compile(r"^\+{0,2}seed=(?P<seed>.*)$")


@dataclass
class Job:
    """One job directory of a sweep, as read from its files (:func:`read_job`).

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
    status: str  # done | incomplete | the status of status.json (invalid, diverged, failed)
    reason: str | None = None
    metrics: dict[str, float | None] = field(default_factory=dict)
    train_seconds: float | None = None
    frames: int | None = None
    updates: int | None = None

    @property
    def config(self) -> str:
        """The job's configuration: its overrides without ``seed`` (``(defaults)``: none)."""
        rest = [o for o in self.overrides if _SEED.match(o) is None]
        return " ".join(rest) if rest else "(defaults)"

    def row(self) -> dict[str, Any]:
        """The job's ``summary.csv`` row."""
        return {
            "job": self.name,
            "config": self.config,
            "seed": self.seed,
            "overrides": " ".join(self.overrides),
            "status": self.status,
            "reason": self.reason,
            **{m: self.metrics.get(m) for m in METRICS},
            "train_seconds": self.train_seconds,
            "frames": self.frames,
            "updates": self.updates,
        }


@dataclass
class Aggregate:
    """One metric of one configuration, across the seeds that finished.

    Examples:
        >>> agg = Aggregate("lr=1e-3", "success_rate", 3, 1, 0.5, 0.5, 0.25, 0.75)
        >>> agg.n, agg.failed, (agg.ci_low, agg.ci_high)
        (3, 1, (0.25, 0.75))
    """

    config: str
    metric: str
    n: int  # finished jobs with a value
    failed: int  # jobs of the configuration that did not finish
    mean: float | None
    iqm: float | None
    ci_low: float | None
    ci_high: float | None


@dataclass
class SweepSummary:
    """What :func:`summarize_sweep` found and wrote: the jobs, the aggregates and the files by
    name (see :func:`summarize_sweep` for an example)."""

    sweep_dir: Path
    jobs: list[Job]
    aggregates: list[Aggregate]
    files: dict[str, Path]

    def aggregate(self, config: str, metric: str = "success_rate") -> Aggregate:
        """The aggregate of ``metric`` for ``config``."""
        for agg in self.aggregates:
            if agg.config == config and agg.metric == metric:
                return agg
        raise KeyError((config, metric))


# ------------------------------------------------------------------ statistics
def interquartile_mean(values: Sequence[float]) -> float:
    """The mean of the middle half: ``floor(n / 4)`` values dropped at each end (as
    ``scipy.stats.trim_mean(values, 0.25)`` and rliable's IQM).

    Examples:
        >>> interquartile_mean([0.0, 1.0, 2.0, 3.0, 100.0, 4.0, 5.0, 6.0])
        3.5
        >>> interquartile_mean([1.0, 2.0])
        1.5
    """
    x = np.sort(np.asarray(values, dtype=float))
    if x.size == 0:
        raise ValueError("interquartile_mean of no values")
    cut = int(0.25 * x.size)
    return float(x[cut : x.size - cut].mean())


def bootstrap_ci(
    values: Sequence[float], confidence: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of the mean (seeded: reproducible).

    Examples:
        >>> low, high = bootstrap_ci([0.2, 0.4, 0.6, 0.8])
        >>> 0.2 <= low < 0.5 < high <= 0.8
        True
        >>> bootstrap_ci([0.5])
        (0.5, 0.5)
    """
    x = np.asarray(values, dtype=float)
    if x.size == 0:
        raise ValueError("bootstrap_ci of no values")
    if x.size == 1:
        return float(x[0]), float(x[0])
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(resamples, x.size))].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


# ------------------------------------------------------------------ reading jobs
def _natural_key(name: str) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _is_job(path: Path) -> bool:
    return any((path / marker).is_file() for marker in _JOB_MARKERS)


def find_jobs(sweep_dir: str | Path) -> list[Path]:
    """The job directories under ``sweep_dir`` (any depth, e.g. Hydra's ``hydra.sweep.subdir``
    set to nested folders), in natural order (``2`` before ``10``). Hidden folders (``.hydra``,
    ``.submitit``) and a job's own sub-folders are not searched; ``sweep_dir`` itself counts
    only when it holds no job below it (a single run directory).

    Examples:
        >>> import tempfile, pathlib
        >>> root = pathlib.Path(tempfile.mkdtemp())
        >>> for job in ("0", "1", "10", "2"):
        ...     (root / job).mkdir()
        ...     _ = (root / job / "eval.json").write_text("{}")
        >>> [p.name for p in find_jobs(root)]
        ['0', '1', '2', '10']
    """
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


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _float(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def _read_overrides(path: Path) -> list[str]:
    try:
        overrides = yaml.safe_load((path / ".hydra" / "overrides.yaml").read_text())
    except (OSError, yaml.YAMLError):
        return []
    return [str(o) for o in overrides] if isinstance(overrides, list) else []


def _read_seed(path: Path, overrides: list[str]) -> int | None:
    for override in overrides:
        match = _SEED.match(override)
        if match is not None:
            try:
                return int(match["seed"])
            except ValueError:
                return None
    for name in ("config.yaml", ".hydra/config.yaml"):
        try:
            saved = yaml.safe_load((path / name).read_text())
        except (OSError, yaml.YAMLError):
            continue
        if isinstance(saved, dict) and isinstance(saved.get("seed"), int):
            return saved["seed"]
    return None


def read_job(path: str | Path, sweep_dir: str | Path | None = None) -> Job:
    """One job directory: overrides, seed, status and the numbers of its ``eval.json``.

    The status is ``done`` when ``eval.json`` exists (and no newer ``status.json``), the
    ``status`` of ``status.json`` (``invalid``, ``interrupted``, ``diverged``, ``failed``) with
    its reason, else ``incomplete`` (still running, or killed).
    """
    path = Path(path)
    root = Path(sweep_dir) if sweep_dir is not None else path.parent
    name = path.relative_to(root).as_posix() if path != root else "."
    overrides = _read_overrides(path)
    job = Job(path, name, overrides, _read_seed(path, overrides), "incomplete")
    eval_file, status_file = path / "eval.json", path / "status.json"
    result = _read_json(eval_file) if eval_file.is_file() else None
    status = _read_json(status_file) if status_file.is_file() else None
    failed_later = (
        status is not None
        and result is not None
        and status_file.stat().st_mtime > eval_file.stat().st_mtime
    )
    if status is not None and (result is None or failed_later):
        job.status = str(status.get("status") or "failed")
        job.reason = None if status.get("reason") is None else str(status["reason"])
    elif result is not None:
        job.status = "done"
    else:
        job.reason = (
            "eval.json is damaged"
            if eval_file.is_file()
            else "no eval.json nor status.json (still running, or killed)"
        )
    if result is not None and job.status == "done":
        task_metrics = result.get("task_metrics") or {}
        job.metrics = {
            "success_rate": _float(result.get("success_rate")),
            "mean_return": _float(result.get("mean_return")),
            "mean_steps": _float(result.get("mean_steps")),
            "value_error": _float(task_metrics.get("value_map_max_abs_error")),
        }
        training = result.get("training") or {}
        job.train_seconds = _float(training.get("seconds"))
        stages = [s for s in training.get("stages") or [] if isinstance(s, dict)]
        if stages:
            job.frames = int(sum(s.get("frames") or 0 for s in stages))
            job.updates = int(sum(s.get("updates") or 0 for s in stages))
    return job


# ------------------------------------------------------------------ aggregation
def _configs(jobs: Iterable[Job]) -> list[str]:
    return list(dict.fromkeys(job.config for job in jobs))


def aggregate_jobs(
    jobs: Sequence[Job], metrics: Sequence[str] = METRICS, seed: int = 0
) -> list[Aggregate]:
    """Mean, interquartile mean and bootstrap 95% CI of each metric per configuration, over
    its finished jobs (a metric no job reports, e.g. the value error of a task without one, is
    left out)."""
    reported = {m for j in jobs for m, v in j.metrics.items() if v is not None}
    metrics = [m for m in metrics if m in reported or m != "value_error"]
    out = []
    for config in _configs(jobs):
        members = [j for j in jobs if j.config == config]
        failed = sum(j.status != "done" for j in members)
        for metric in metrics:
            values = [
                v
                for j in members
                if j.status == "done" and (v := j.metrics.get(metric)) is not None
            ]
            if values:
                low, high = bootstrap_ci(values, seed=seed)
                mean, iqm = float(np.mean(values)), interquartile_mean(values)
            else:
                mean = iqm = low = high = None
            out.append(Aggregate(config, metric, len(values), failed, mean, iqm, low, high))
    return out


# ------------------------------------------------------------------ writing
def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _write_csv(path: Path, header: Sequence[str], rows: Iterable[dict[str, Any]]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(header))
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row[k] for k in header})


def _short_labels(configs: Sequence[str]) -> dict[str, str]:
    """Each configuration without the overrides that every configuration shares."""
    parts = {c: c.split(" ") if c != "(defaults)" else [] for c in configs}
    common = set.intersection(*(set(p) for p in parts.values())) if parts else set()
    labels = {}
    for config, items in parts.items():
        rest = [p for p in items if p not in common]
        labels[config] = " ".join(rest) if rest else config
    return labels


def _cell(text: Any) -> str:
    return _fmt(text).replace("|", "\\|").replace("\n", " ")


def _markdown(summary: SweepSummary) -> str:
    jobs, aggs = summary.jobs, summary.aggregates
    counts: dict[str, int] = defaultdict(int)
    for job in jobs:
        counts[job.status] += 1
    status = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    lines = [
        f"# Sweep summary: {summary.sweep_dir}",
        "",
        f"{len(jobs)} jobs ({status or 'none'}), {len(_configs(jobs))} configurations "
        "(a configuration: the overrides without `seed`).",
        "",
        "## Per configuration, across seeds",
        "",
        "Mean, interquartile mean (IQM: the middle half of the seeds) and a percentile bootstrap "
        "95% confidence interval of the mean (2000 resamples, seeded) over the finished jobs.",
        "",
        "| configuration | metric | finished | failed | mean | IQM | 95% CI |",
        "|---|---|---|---|---|---|---|",
    ]
    for agg in aggs:
        ci = "" if agg.ci_low is None else f"[{agg.ci_low:.3f}, {agg.ci_high:.3f}]"
        lines.append(
            f"| {_cell(agg.config)} | {agg.metric} | {agg.n} | {agg.failed} | {_fmt(agg.mean)} | "
            f"{_fmt(agg.iqm)} | {ci} |"
        )
    lines += [
        "",
        "## Jobs",
        "",
        "| job | overrides | status | success | mean steps | value error | train s | frames "
        "| reason |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for job in jobs:
        m = job.metrics
        lines.append(
            f"| {_cell(job.name)} | {_cell(' '.join(job.overrides))} | {job.status} | "
            f"{_fmt(m.get('success_rate'))} | {_fmt(m.get('mean_steps'), 1)} | "
            f"{_fmt(m.get('value_error'))} | {_fmt(job.train_seconds, 1)} | {_fmt(job.frames)} | "
            f"{_cell(job.reason)} |"
        )
    figures = [name for name in (CURVES_PNG, FINAL_PNG) if name in summary.files]
    if figures:
        lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ figures
def _read_curves(metrics_csv: Path) -> dict[str, list[tuple[float, float]]]:
    curves: dict[str, list[tuple[float, float]]] = defaultdict(list)
    try:
        with metrics_csv.open(newline="") as handle:
            for row in csv.DictReader(handle):
                name = row.get("name") or ""
                if _CURVE.match(name) is None:
                    continue
                step, value = _float(row.get("step")), _float(row.get("value"))
                if step is not None and value is not None:
                    curves[name].append((step, value))
    except OSError:
        return {}
    return {name: sorted(points) for name, points in curves.items()}


def _curve_order(name: str) -> tuple[int, int]:
    match = _CURVE.match(name)
    assert match is not None
    if match["scope"] == "task":
        return (0, 0)
    if match["phase"] is not None:
        return (2, int(match["phase"]))
    return (1, int(match["stage"]))


def _curve_title(name: str) -> str:
    match = _CURVE.match(name)
    assert match is not None
    if match["scope"] == "task":
        return "whole task (eval.probe), frames of all stages"
    if match["phase"] is not None:
        return f"joint phase {match['phase']}, frames of the phase"
    return f"stage {match['stage']}, frames in the stage"


def _forward_fill(points: list[tuple[float, float]], grid: np.ndarray) -> np.ndarray:
    """The value of the last evaluation at or before each grid step (NaN before the first);
    a stage that stopped early keeps its last evaluation."""
    steps = np.array([p[0] for p in points])
    values = np.array([p[1] for p in points])
    idx = np.searchsorted(steps, grid, side="right") - 1
    out = np.where(idx >= 0, values[np.clip(idx, 0, None)], np.nan)
    return out


def plot_sweep_curves(
    jobs: Sequence[Job], out: str | Path, labels: dict[str, str] | None = None
) -> Path | None:
    """Evaluation success against frames, one panel per stage (and the whole-task probe), one
    line per configuration: the mean over its seeds and a band from the lowest to the highest.
    Returns ``None`` when no finished job has such curves."""
    from matplotlib.figure import Figure

    from torchrl_stages.plots import DPI

    per_job = {j.name: _read_curves(j.path / "metrics.csv") for j in jobs if j.status == "done"}
    names = sorted({n for curves in per_job.values() for n in curves}, key=_curve_order)
    if not names:
        return None
    configs = _configs(j for j in jobs if j.name in per_job)
    labels = labels or _short_labels(configs)
    ncols = min(3, len(names))
    nrows = math.ceil(len(names) / ncols)
    fig = Figure(figsize=(5.2 * ncols, 3.6 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, name in zip(axes, names, strict=False):
        for c, config in enumerate(configs):
            seeds = [
                per_job[j.name][name]
                for j in jobs
                if j.config == config and j.name in per_job and name in per_job[j.name]
            ]
            if not seeds:
                continue
            grid = np.unique(np.concatenate([[p[0] for p in s] for s in seeds]))
            values = np.stack([_forward_fill(s, grid) for s in seeds])
            with warnings.catch_warnings():  # all-NaN columns: before a seed's first point
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(values, axis=0)
                low, high = np.nanmin(values, axis=0), np.nanmax(values, axis=0)
            color = f"C{c % 10}"
            label = f"{labels.get(config, config)} ({len(seeds)} seed{'s' * (len(seeds) > 1)})"
            ax.plot(grid, mean, color=color, label=label, marker="o" if grid.size == 1 else None)
            if len(seeds) > 1:
                ax.fill_between(grid, low, high, color=color, alpha=0.2, linewidth=0)
        ax.set_title(_curve_title(name), fontsize=10)
        ax.set_xlabel("frames")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    for ax in axes[len(names) :]:
        ax.set_visible(False)
    handles, texts = axes[0].get_legend_handles_labels()
    fig.legend(handles, texts, loc="lower center", ncol=min(3, max(1, len(texts))), fontsize=8)
    fig.suptitle("greedy evaluation success per configuration (line: mean, band: min-max)")
    fig.tight_layout(rect=(0, 0.06 + 0.02 * math.ceil(len(texts) / 3), 1, 0.97))
    path = Path(out)
    fig.savefig(path, dpi=DPI, format="png")
    return path


def plot_sweep_final(
    jobs: Sequence[Job],
    aggregates: Sequence[Aggregate],
    out: str | Path,
    labels: dict[str, str] | None = None,
) -> Path | None:
    """The final whole-task metrics per configuration (one row each): every seed (dots), the
    mean (bar) and its bootstrap 95% CI. Returns ``None`` when no job finished."""
    from matplotlib.figure import Figure

    from torchrl_stages.plots import DPI

    done = [j for j in jobs if j.status == "done"]
    if not done:
        return None
    configs = _configs(done)
    labels = labels or _short_labels(configs)
    metrics = [
        m
        for m in ("success_rate", "mean_steps", "value_error")
        if any(j.metrics.get(m) is not None for j in done)
    ]
    by_key = {(a.config, a.metric): a for a in aggregates}
    height = max(2.6, 0.45 * len(configs) + 1.4)
    fig = Figure(figsize=(4.2 * len(metrics) + 2.5, height))
    axes = fig.subplots(1, len(metrics), squeeze=False).ravel()
    ys = np.arange(len(configs))
    for ax, metric in zip(axes, metrics, strict=True):
        for y, config in zip(ys, configs, strict=True):
            values = [
                v for j in done if j.config == config and (v := j.metrics.get(metric)) is not None
            ]
            agg = by_key.get((config, metric))
            color = f"C{y % 10}"
            if agg is not None and agg.mean is not None:
                ax.barh(y, agg.mean, color=color, alpha=0.35, height=0.6)
                ax.errorbar(
                    agg.mean,
                    y,
                    xerr=[[agg.mean - agg.ci_low], [agg.ci_high - agg.mean]],
                    color="k",
                    capsize=4,
                    linewidth=1.2,
                )
            ax.plot(values, [y] * len(values), "o", color=color, markeredgecolor="k", zorder=3)
        ax.set_yticks(ys, [labels.get(c, c) for c in configs] if ax is axes[0] else [""] * len(ys))
        ax.invert_yaxis()
        ax.set_title(metric)
        ax.grid(axis="x", alpha=0.3)
        if metric == "success_rate":
            ax.set_xlim(0, 1.05)
    fig.suptitle("final whole-task evaluation per configuration (dots: seeds, bar: mean, 95% CI)")
    fig.tight_layout()
    path = Path(out)
    fig.savefig(path, dpi=DPI, format="png")
    return path


# ------------------------------------------------------------------ entry point
def summarize_sweep(sweep_dir: str | Path, *, plots: bool = True, seed: int = 0) -> SweepSummary:
    """Reads every job directory under ``sweep_dir`` and writes the sweep's summary there:
    ``summary.csv``, ``summary_configs.csv``, ``summary.md`` and (``plots``)
    ``summary_curves.png`` and ``summary_final.png``. ``seed`` seeds the bootstrap.

    Examples:
        >>> import json, tempfile, pathlib
        >>> sweep = pathlib.Path(tempfile.mkdtemp())
        >>> for job, (seed, success) in enumerate([(0, 1.0), (1, 0.5)]):
        ...     (sweep / f"{job}/.hydra").mkdir(parents=True)
        ...     _ = (sweep / f"{job}/.hydra/overrides.yaml").write_text(f"- seed={seed}\\n")
        ...     _ = (sweep / f"{job}/eval.json").write_text(json.dumps(
        ...         {"success_rate": success, "mean_return": 1.0, "mean_steps": 10.0}))
        >>> summary = summarize_sweep(sweep, plots=False)
        >>> [job.status for job in summary.jobs], summary.aggregate("(defaults)").mean
        (['done', 'done'], 0.75)
        >>> sorted(summary.files)
        ['summary.csv', 'summary.md', 'summary_configs.csv']
    """
    root = Path(sweep_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a directory")
    jobs = [read_job(path, root) for path in find_jobs(root)]
    aggregates = aggregate_jobs(jobs, seed=seed)
    summary = SweepSummary(root, jobs, aggregates, {})
    _write_csv(root / SUMMARY_CSV, COLUMNS, (job.row() for job in jobs))
    summary.files[SUMMARY_CSV] = root / SUMMARY_CSV
    _write_csv(
        root / CONFIGS_CSV,
        ("config", "metric", "n", "failed", "mean", "iqm", "ci_low", "ci_high"),
        (vars(agg) for agg in aggregates),
    )
    summary.files[CONFIGS_CSV] = root / CONFIGS_CSV
    if plots:
        labels = _short_labels(_configs(jobs))
        for name, made in (
            (CURVES_PNG, plot_sweep_curves(jobs, root / CURVES_PNG, labels)),
            (FINAL_PNG, plot_sweep_final(jobs, aggregates, root / FINAL_PNG, labels)),
        ):
            if made is not None:
                summary.files[name] = made
    (root / SUMMARY_MD).write_text(_markdown(summary))
    summary.files[SUMMARY_MD] = root / SUMMARY_MD
    return summary
