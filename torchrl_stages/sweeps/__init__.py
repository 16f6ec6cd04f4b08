"""Sweep summaries of a directory of runs (any launcher's, a study's trials, or gathered by
hand): ``summary.csv``, ``summary_configs.csv``, ``summary.md`` (statistics across seeds on
rliable) and figures. ``stages-train -m``, ``stages-tune`` and ``stages-report`` write them."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from torchrl_stages.sweeps.figures import (
    plot_performance_profile,
    plot_sweep_curves,
    plot_sweep_final,
    short_labels,
)
from torchrl_stages.sweeps.jobs import Job, configs, find_jobs, read_job
from torchrl_stages.sweeps.stats import Aggregate, aggregate_jobs
from torchrl_stages.sweeps.tables import markdown, write_configs_csv, write_jobs_csv


@dataclass
class SweepSummary:
    """What :func:`summarize_sweep` found and wrote: the jobs, the aggregates, the files."""

    sweep_dir: Path
    jobs: list[Job]
    aggregates: list[Aggregate]
    files: dict[str, Path]

    def aggregate(self, config: str, metric: str = "success_rate") -> Aggregate:
        return next(a for a in self.aggregates if (a.config, a.metric) == (config, metric))


def summarize_sweep(sweep_dir: str | Path, *, plots: bool = True, seed: int = 0) -> SweepSummary:
    """Reads the jobs under ``sweep_dir`` and writes the summary there; ``seed`` seeds the
    bootstrap."""
    root = Path(sweep_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a directory")
    jobs = [read_job(path, root) for path in find_jobs(root)]
    aggregates = aggregate_jobs(jobs, seed=seed)
    files = {name: root / name for name in ("summary.csv", "summary_configs.csv")}
    write_jobs_csv(files["summary.csv"], jobs)
    write_configs_csv(files["summary_configs.csv"], aggregates)
    figures = []
    if plots:
        labels = short_labels(configs(jobs))
        for name, made in (
            ("summary_curves.png", plot_sweep_curves(jobs, root / "summary_curves.png", labels)),
            (
                "summary_final.png",
                plot_sweep_final(jobs, aggregates, root / "summary_final.png", labels),
            ),
            (
                "summary_profile.png",
                plot_performance_profile(jobs, root / "summary_profile.png", labels, seed=seed),
            ),
        ):
            if made is not None:
                files[name] = made
                figures.append(name)
    files["summary.md"] = root / "summary.md"
    files["summary.md"].write_text(markdown(root, jobs, aggregates, figures))
    return SweepSummary(root, jobs, aggregates, files)


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
