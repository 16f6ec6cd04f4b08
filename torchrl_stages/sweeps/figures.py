"""A sweep's figures: learning curves, final metrics and performance profiles per configuration
(on a matplotlib ``Figure``, no pyplot state: safe in a Hydra callback)."""

from __future__ import annotations

import math
import textwrap
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from torchrl_stages.metric_names import STAGE, TASK, MetricName, is_loop_evaluation, parse_metric
from torchrl_stages.plots import read_metrics, save_figure
from torchrl_stages.sweeps.jobs import Job, result_metrics
from torchrl_stages.sweeps.jobs import configs as configs_of
from torchrl_stages.sweeps.stats import Aggregate, finished_scores, performance_profiles


def short_labels(names: Sequence[str]) -> dict[str, str]:
    """Each configuration without the overrides all of them share."""
    common = set.intersection(*(set(c.split(" ")) for c in names)) if names else set()
    return {c: " ".join(p for p in c.split(" ") if p not in common) or c for c in names}


def _read_curves(metrics_csv: Path) -> dict[MetricName, list[tuple[float, float]]]:
    """A run's curves of the summary: the success of the whole-task probe and of each loop."""
    try:
        points = read_metrics(metrics_csv)
    except OSError:
        return {}
    probe = MetricName("eval", TASK, None, "success_rate")
    return {
        parse_metric(name): sorted(p)
        for name, p in points.items()
        if is_loop_evaluation(name) or parse_metric(name) == probe
    }


def _curve_order(curve: MetricName) -> tuple[int, str, int]:
    """The whole task first, then stages, then other loops' phases."""
    return (0, "", 0) if curve.index is None else (curve.scope != STAGE, curve.scope, curve.index)


def _curve_title(curve: MetricName) -> str:
    if curve.index is None:
        return "whole task (eval.probe), frames of all stages"
    if curve.scope == STAGE:
        return f"stage {curve.index}, frames in the stage"
    return f"{curve.scope} phase {curve.index}, frames of the phase"


def _forward_fill(points: list[tuple[float, float]], grid: np.ndarray) -> np.ndarray:
    """The last evaluation at or before each grid step (NaN before the first)."""
    steps, values = np.array(points).T
    idx = np.searchsorted(steps, grid, side="right") - 1
    return np.where(idx >= 0, values[np.clip(idx, 0, None)], np.nan)


def plot_sweep_curves(jobs: Sequence[Job], out: str | Path) -> Path | None:
    """Evaluation success against frames, a panel per stage and the whole-task probe, a line per
    configuration (mean over seeds, band min-max); ``None`` without such curves."""
    from matplotlib.figure import Figure

    runs: dict[str, list[dict]] = {}  # each finished seed's curves, by configuration
    for job in jobs:
        if job.status == "done":
            runs.setdefault(job.config, []).append(_read_curves(job.path / "metrics.csv"))
    names = sorted({n for seeds in runs.values() for s in seeds for n in s}, key=_curve_order)
    if not names:
        return None
    labels = short_labels(configs_of(jobs))
    ncols, nrows = min(3, len(names)), math.ceil(len(names) / 3)
    fig = Figure(figsize=(5.2 * ncols, 3.6 * nrows + 0.6))
    for i, name in enumerate(names):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        for c, (config, curves) in enumerate(runs.items()):
            seeds = [s[name] for s in curves if name in s]
            if not seeds:
                continue
            grid = np.unique(np.concatenate([[p[0] for p in s] for s in seeds]))
            values = np.stack([_forward_fill(s, grid) for s in seeds])
            # all-NaN columns: before a seed's first point
            with warnings.catch_warnings(action="ignore", category=RuntimeWarning):
                mean = np.nanmean(values, axis=0)
                low, high = np.nanmin(values, axis=0), np.nanmax(values, axis=0)
            color = f"C{c % 10}"
            label = f"{labels[config]} ({len(seeds)} seed{'s' * (len(seeds) > 1)})"
            ax.plot(grid, mean, color=color, label=label, marker="o" if grid.size == 1 else None)
            if len(seeds) > 1:
                ax.fill_between(grid, low, high, color=color, alpha=0.2, linewidth=0)
        ax.set_title(_curve_title(name), fontsize=10)
        ax.set(xlabel="frames", ylabel="success rate", ylim=(-0.05, 1.05))
        ax.grid(alpha=0.3)
    handles, texts = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, texts, loc="lower center", ncol=min(3, max(1, len(texts))), fontsize=8)
    fig.suptitle("greedy evaluation success per configuration (line: mean, band: min-max)")
    fig.tight_layout(rect=(0, 0.06 + 0.02 * math.ceil(len(texts) / 3), 1, 0.97))
    return save_figure(fig, out)


def plot_sweep_final(
    jobs: Sequence[Job], aggregates: Sequence[Aggregate], out: str | Path
) -> Path | None:
    """The final whole-task metrics per configuration: seeds, mean and its 95% CI."""
    from matplotlib.figure import Figure

    done = [j for j in jobs if j.status == "done"]
    if not done:
        return None
    configs = configs_of(done)
    labels = short_labels(configs_of(jobs))
    shown = [m for m in result_metrics(done) if m != "mean_return"]  # and the task's headline
    metrics = [m for m in shown if any(j.metrics.get(m) is not None for j in done)]
    by_key = {(a.config, a.metric): a for a in aggregates}
    fig = Figure(figsize=(4.2 * len(metrics) + 2.5, max(2.6, 0.45 * len(configs) + 1.4)))
    axes = fig.subplots(1, len(metrics), squeeze=False).ravel()
    ys = np.arange(len(configs))
    for ax, metric in zip(axes, metrics, strict=True):
        for y, config in zip(ys, configs, strict=True):
            values = finished_scores(done, config, metric).ravel()
            agg = by_key.get((config, metric))
            color = f"C{y % 10}"
            if agg is not None and agg.mean is not None:
                ax.barh(y, agg.mean, color=color, alpha=0.35, height=0.6)
                xerr = [[agg.mean - agg.ci_low], [agg.ci_high - agg.mean]]
                ax.errorbar(agg.mean, y, xerr=xerr, color="k", capsize=4, linewidth=1.2)
            ax.plot(values, [y] * len(values), "o", color=color, markeredgecolor="k", zorder=3)
        ax.set_yticks(ys, [labels[c] for c in configs] if ax is axes[0] else [""] * len(ys))
        ax.invert_yaxis()
        ax.set_title(metric)
        ax.grid(axis="x", alpha=0.3)
        if metric == "success_rate":
            ax.set_xlim(0, 1.05)
    fig.suptitle("final whole-task evaluation per configuration (dots: seeds, bar: mean, 95% CI)")
    fig.tight_layout()
    return save_figure(fig, out)


def plot_performance_profile(jobs: Sequence[Job], out: str | Path, seed: int = 0) -> Path | None:
    """The performance profile of the success rate per configuration with its 95% band (not
    ``rliable.plot_utils``: it imports pyplot)."""
    from matplotlib.figure import Figure

    taus = np.linspace(0.0, 1.0, 101)
    profiles = performance_profiles(jobs, taus, seed)
    if not profiles:
        return None
    labels = short_labels(configs_of(jobs))
    # the legend below the plot, labels wrapped to its 7-inch width: they hide no curve
    texts = [textwrap.fill(labels[c], 90) for c in profiles]
    lines = sum(t.count("\n") + 1 for t in texts)
    fig = Figure(figsize=(7.0, 4.2 + 0.17 * lines), layout="constrained")
    ax = fig.subplots()
    for c, (text, (profile, (low, high))) in enumerate(zip(texts, profiles.values(), strict=True)):
        color = f"C{c % 10}"
        ax.plot(taus, profile, color=color, linewidth=2, label=text)
        ax.fill_between(taus, low, high, color=color, alpha=0.15, linewidth=0)
    ax.set(xlabel="success_rate threshold tau", xlim=(0.0, 1.0), ylim=(-0.02, 1.02))
    ax.set_ylabel("fraction of runs with success_rate > tau")
    ax.grid(alpha=0.3)
    fig.legend(fontsize=8, loc="outside lower center")
    fig.suptitle("performance profile per configuration (band: 95% bootstrap CI)")
    return save_figure(fig, out)
