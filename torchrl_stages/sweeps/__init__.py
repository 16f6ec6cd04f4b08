"""Sweep summaries of a directory of runs (any launcher's, a study's trials, or gathered by
hand): ``summary.csv``, ``summary_configs.csv``, ``summary.md`` (statistics across seeds on
rliable) and figures. ``stages-train -m``, ``stages-tune`` and ``stages-report`` write them."""

from __future__ import annotations

import csv
import sys
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from torchrl_stages.sweeps import figures
from torchrl_stages.sweeps.jobs import Job, configs, find_jobs, read_job, result_metrics
from torchrl_stages.sweeps.stats import REPS, Aggregate, aggregate_jobs


def _fmt(value: Any, digits: int = 3) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return "" if value is None else str(value)


def _cell(text: Any) -> str:
    return _fmt(text).replace("|", "\\|").replace("\n", " ")


def _write_csv(path: Path, header: Sequence[str], rows: Iterable[dict[str, Any]]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(header))
        writer.writeheader()
        writer.writerows(rows)  # None as an empty cell


def _interval(low: float | None, high: float | None) -> str:
    return "" if low is None else f"[{low:.3f}, {high:.3f}]"


def markdown(
    sweep_dir: Path, jobs: Sequence[Job], aggregates: Sequence[Aggregate], figures: Sequence[str]
) -> str:
    """``summary.md``: the per-configuration statistics, every job, and the figures."""
    counts = Counter(job.status for job in jobs)
    status = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    metrics = [m for m in result_metrics(jobs) if m != "mean_return"]
    lines = [
        f"# Sweep summary: {sweep_dir}",
        "",
        f"{len(jobs)} jobs ({status or 'none'}), {len(configs(jobs))} configurations "
        "(a configuration: the overrides without `seed`).",
        "",
        "## Per configuration, across seeds",
        "",
        "Mean and interquartile mean (IQM: the middle half of the seeds) over the finished jobs, "
        f"each with a stratified-bootstrap 95% confidence interval (rliable, {REPS} resamples, "
        "seeded).",
        "",
        "| configuration | metric | finished | failed | mean | 95% CI | IQM | 95% CI |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for agg in aggregates:
        lines.append(
            f"| {_cell(agg.config)} | {agg.metric} | {agg.n} | {agg.failed} | {_fmt(agg.mean)} | "
            f"{_interval(agg.ci_low, agg.ci_high)} | {_fmt(agg.iqm)} | "
            f"{_interval(agg.iqm_low, agg.iqm_high)} |"
        )
    columns = ["job", "overrides", "status", *metrics, "train s", "frames", "reason"]
    lines += ["", "## Jobs", "", "| " + " | ".join(columns) + " |", "|---" * len(columns) + "|"]
    for job in jobs:
        values = [_fmt(job.metrics.get(m), 1 if m == "mean_steps" else 3) for m in metrics]
        cells = [_cell(job.name), _cell(" ".join(job.overrides)), job.status, *values]
        cells += [_fmt(job.train_seconds, 1), _fmt(job.frames), _cell(job.reason)]
        lines.append("| " + " | ".join(cells) + " |")
    if figures:
        lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


@dataclass
class SweepSummary:
    """What :func:`summarize_sweep` found and wrote: the jobs, the aggregates, the files."""

    jobs: list[Job]
    aggregates: list[Aggregate]
    files: dict[str, Path]


def summarize_sweep(sweep_dir: str | Path, *, plots: bool = True, seed: int = 0) -> SweepSummary:
    """Reads the jobs under ``sweep_dir`` and writes their summary there (``seed``: bootstrap)."""
    root = Path(sweep_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a directory")
    jobs = [read_job(path, root) for path in find_jobs(root)]
    aggregates = aggregate_jobs(jobs, seed=seed)
    files = {name: root / name for name in ("summary.csv", "summary_configs.csv")}
    metrics = result_metrics(jobs)
    header = list(Job(Path(), "", [], None, "").row(metrics))
    _write_csv(files["summary.csv"], header, (job.row(metrics) for job in jobs))
    header = [f.name for f in fields(Aggregate)]
    _write_csv(files["summary_configs.csv"], header, (vars(agg) for agg in aggregates))
    drawn = {}
    if plots:
        made = (
            figures.plot_sweep_curves(jobs, root / "summary_curves.png"),
            figures.plot_sweep_final(jobs, aggregates, root / "summary_final.png"),
            figures.plot_performance_profile(jobs, root / "summary_profile.png", seed=seed),
        )
        drawn = {path.name: path for path in made if path is not None}
    files |= drawn
    files["summary.md"] = root / "summary.md"
    files["summary.md"].write_text(markdown(root, jobs, aggregates, list(drawn)))
    return SweepSummary(jobs, aggregates, files)


def summarize_or_say(sweep_dir: Path, plots: bool, failure: str) -> SweepSummary | None:
    """:func:`summarize_sweep` where there are jobs; a failure is printed after ``failure``,
    never raised: a summary must not hide the outcome of the runs."""
    if not find_jobs(sweep_dir):
        return None
    try:
        return summarize_sweep(sweep_dir, plots=plots)
    except Exception as err:  # noqa: BLE001
        print(f"{failure} ({type(err).__name__}: {err})", file=sys.stderr)
        return None
