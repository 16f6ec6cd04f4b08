"""Sweep summaries: one table, statistics across seeds and figures for a directory of runs.

A sweep directory holds one directory per job, whatever made it (Hydra's basic, joblib,
submitit or Ray launcher, the trials of a ``stages-tune`` study, or runs copied together by
hand).
:func:`summarize_sweep` reads them (:mod:`~torchrl_stages.sweeps.jobs`), computes statistics
across seeds on rliable (:mod:`~torchrl_stages.sweeps.stats`), and writes into the sweep
directory the tables (:mod:`~torchrl_stages.sweeps.tables`) and figures
(:mod:`~torchrl_stages.sweeps.figures`):

* ``summary.csv``: one row per job (its overrides, status and failure reason, whole-task success
  rate, mean return and steps, the task's headline metrics, training seconds, frames, updates);
* ``summary_configs.csv`` and ``summary.md``: per configuration (the overrides without
  ``seed``), across seeds, the mean and the interquartile mean of each metric, each with a
  stratified-bootstrap 95% confidence interval (seeded: the same files give the same numbers);
* ``summary_curves.png`` (learning curves per configuration: the mean over seeds and a band from
  the lowest to the highest seed), ``summary_final.png`` (the final metrics per configuration:
  each seed, the mean and its confidence interval) and ``summary_profile.png`` (the performance
  profile of the success rate).

``stages-train -m`` writes them when a sweep ends (:class:`torchrl_stages.cli.SweepSummaryCallback`,
configured in ``hydra.callbacks``), ``stages-tune`` when a study's trials end
(:mod:`torchrl_stages.tune`), ``stages-report DIR`` on demand.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from torchrl_stages.sweeps.figures import (
    plot_performance_profile,
    plot_sweep_curves,
    plot_sweep_final,
    short_labels,
)
from torchrl_stages.sweeps.jobs import METRICS, Job, configs, find_jobs, read_job
from torchrl_stages.sweeps.stats import Aggregate, aggregate_jobs, performance_profiles
from torchrl_stages.sweeps.tables import markdown, write_configs_csv, write_jobs_csv

__all__ = [
    "METRICS",
    "Aggregate",
    "Job",
    "SweepSummary",
    "aggregate_jobs",
    "find_jobs",
    "performance_profiles",
    "plot_performance_profile",
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
PROFILE_PNG = "summary_profile.png"


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


def summarize_sweep(sweep_dir: str | Path, *, plots: bool = True, seed: int = 0) -> SweepSummary:
    """Reads every job directory under ``sweep_dir`` and writes the sweep's summary there:
    ``summary.csv``, ``summary_configs.csv``, ``summary.md`` and (``plots``) the figures
    ``summary_curves.png``, ``summary_final.png`` and ``summary_profile.png``. ``seed`` seeds
    the bootstrap.

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
    write_jobs_csv(root / SUMMARY_CSV, jobs)
    write_configs_csv(root / CONFIGS_CSV, aggregates)
    summary.files.update({SUMMARY_CSV: root / SUMMARY_CSV, CONFIGS_CSV: root / CONFIGS_CSV})
    if plots:
        labels = short_labels(configs(jobs))
        for name, made in (
            (CURVES_PNG, plot_sweep_curves(jobs, root / CURVES_PNG, labels)),
            (FINAL_PNG, plot_sweep_final(jobs, aggregates, root / FINAL_PNG, labels)),
            (PROFILE_PNG, plot_performance_profile(jobs, root / PROFILE_PNG, labels, seed=seed)),
        ):
            if made is not None:
                summary.files[name] = made
    figures = [name for name in (CURVES_PNG, FINAL_PNG, PROFILE_PNG) if name in summary.files]
    (root / SUMMARY_MD).write_text(markdown(root, jobs, aggregates, figures))
    summary.files[SUMMARY_MD] = root / SUMMARY_MD
    return summary
