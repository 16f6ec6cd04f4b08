"""Figures in the style of the paper's Fig. 2: trajectories, value maps and learning curves.

Figures are built with :class:`matplotlib.figure.Figure` and written with ``savefig``, so no
pyplot state and no backend switching is involved: importing this module leaves the user's
matplotlib backend alone.
"""

from __future__ import annotations

import csv
import math
import re
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle

__all__ = [
    "plot_arm_figure",
    "plot_cargo_figure",
    "plot_grid_trajectories",
    "plot_learning_curves",
    "plot_value_map",
]

DPI = 120
_METRIC = re.compile(r"^(?P<kind>[^/]+)/stage_(?P<stage>\d+)/(?P<metric>.+)$")


def _save(fig: Figure, out: str | Path) -> Path:
    """Write ``fig`` as PNG to ``out`` (creating parent folders) and return the path."""
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, format="png")
    return path


def _stage_boundaries(ax: Axes, n_cols: int, stage_width: int, color: str = "k") -> None:
    """Dashed vertical lines between stages (cell edges lie at half-integers)."""
    for edge in range(stage_width, n_cols, stage_width):
        ax.axvline(edge - 0.5, color=color, linestyle="--", linewidth=1.5)


def _mark_target(ax: Axes, target: tuple[int, int], color: str = "gold") -> None:
    """Star on the target cell, given as (row, col)."""
    row, col = target
    ax.plot(
        col,
        row,
        marker="*",
        markersize=18,
        color=color,
        markeredgecolor="k",
        linestyle="none",
        label="target",
        zorder=5,
    )


def plot_grid_trajectories(
    paths: Sequence[Sequence[tuple[int, int]]],
    *,
    size: int,
    stage_width: int,
    target: tuple[int, int],
    out: str | Path,
    title: str = "",
    labels: Sequence[str] | None = None,
) -> Path:
    """Draw greedy trajectories, each a sequence of (row, col) cells, over the grid.

    Row 0 is at the top and column 0 at the left. Each path starts with a ``^`` marker; the
    target gets a star. With ``labels`` (one per path) a legend is added. Returns the PNG path.
    """
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"got {len(labels)} labels for {len(paths)} paths")
    fig = Figure(figsize=(6.5, 6.5))
    ax = fig.add_subplot()
    ticks = np.arange(-0.5, size, 1.0)
    ax.set_xticks(ticks, minor=True)
    ax.set_yticks(ticks, minor=True)
    ax.grid(which="minor", color="0.85", linewidth=0.5)
    ax.tick_params(which="minor", length=0)
    ax.set_xlim(-0.5, size - 0.5)
    ax.set_ylim(size - 0.5, -0.5)  # inverted: row 0 at the top
    ax.set_aspect("equal")
    _stage_boundaries(ax, size, stage_width)
    for k, start in enumerate(range(0, size, stage_width)):
        centre = start + (min(start + stage_width, size) - start - 1) / 2
        ax.text(centre, -0.7, f"stage {k}", ha="center", va="bottom", fontsize=9)
    colors = [f"C{i % 10}" for i in range(len(paths))]
    for i, path in enumerate(paths):
        cells = np.asarray(path, dtype=float).reshape(-1, 2)
        if len(cells) == 0:
            continue
        label = labels[i] if labels is not None else None
        ax.plot(cells[:, 1], cells[:, 0], color=colors[i], linewidth=2, alpha=0.85, label=label)
        ax.plot(
            cells[0, 1],
            cells[0, 0],
            marker="^",
            markersize=10,
            color=colors[i],
            markeredgecolor="k",
            linestyle="none",
            zorder=4,
        )
    _mark_target(ax, target)
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    if title:
        ax.set_title(title, pad=22)
    if labels is not None and len(paths) > 0:
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    return _save(fig, out)


def plot_value_map(
    values: np.ndarray,
    *,
    stage_width: int,
    target: tuple[int, int] | None = None,
    out: str | Path,
    title: str = "",
) -> Path:
    """Heat map of a (size, size) state-value array, row 0 at the top; returns the PNG path.

    Non-finite entries (e.g. unvisited cells) are left blank.
    """
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 2:
        raise ValueError(f"values must be 2-D (rows, cols), got shape {arr.shape}")
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot()
    image = ax.imshow(
        np.ma.masked_invalid(arr), origin="upper", cmap="viridis", interpolation="nearest"
    )
    fig.colorbar(image, ax=ax, label="V(s)")
    _stage_boundaries(ax, arr.shape[1], stage_width, color="w")
    if target is not None:
        _mark_target(ax, target, color="red")
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save(fig, out)


def _read_metrics(
    metrics_csv: str | Path, names: Sequence[str]
) -> dict[str, dict[tuple[str, int], list[tuple[float, float]]]]:
    """``{metric: {(kind, stage): [(step, value), ...]}}`` for per-stage rows named in ``names``."""
    wanted = set(names)
    series: dict[str, dict[tuple[str, int], list[tuple[float, float]]]] = defaultdict(
        lambda: defaultdict(list)
    )
    with open(metrics_csv, newline="") as handle:
        for row in csv.DictReader(handle):
            match = _METRIC.match(row.get("name") or "")
            if match is None or match["metric"] not in wanted:
                continue
            try:
                step, value = float(row["step"]), float(row["value"])
            except (KeyError, TypeError, ValueError):
                continue
            series[match["metric"]][(match["kind"], int(match["stage"]))].append((step, value))
    return series


def plot_learning_curves(
    metrics_csv: str | Path,
    out: str | Path,
    names: Sequence[str] = ("episode_return", "episode_success", "loss", "success_rate"),
) -> Path | None:
    """One subplot per metric in ``names``, one line per stage against frames in that stage.

    Reads a ``name,step,value`` CSV whose names look like ``train/stage_3/loss``; rows not tied
    to a stage (e.g. ``eval/task/...``) are ignored. Returns None when nothing matches.
    """
    series = _read_metrics(metrics_csv, names)
    metrics = [name for name in names if name in series]
    if not metrics:
        return None
    ncols = min(2, len(metrics))
    nrows = math.ceil(len(metrics) / ncols)
    fig = Figure(figsize=(6 * ncols, 3.8 * nrows))
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, metric in zip(axes, metrics, strict=False):
        lines = series[metric]
        kinds = {kind for kind, _ in lines}
        for kind, stage in sorted(lines, key=lambda key: (key[1], key[0])):
            points = sorted(lines[(kind, stage)])
            steps, vals = zip(*points, strict=True)
            label = f"stage {stage}" if len(kinds) == 1 else f"stage {stage} ({kind})"
            ax.plot(
                steps,
                vals,
                color=f"C{stage % 10}",
                label=label,
                linestyle="-" if kind == "train" else "--",
                marker="o" if len(points) == 1 else None,
            )
        ax.set_title(metric)
        ax.set_xlabel("frames in stage")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    fig.tight_layout()
    return _save(fig, out)


def plot_arm_figure(
    effector_paths: Sequence[Sequence[Sequence[float]]],
    fine_values: np.ndarray,
    *,
    target: Sequence[float],
    half_width: float,
    switch_distance: float,
    out: str | Path,
) -> Path:
    """The manipulator panel (paper's Fig. 4(b)): effector paths and the fine stage's value.

    ``fine_values`` is an ``n x n`` map of effector positions within ``half_width`` of the
    target (x along columns, y along rows, y increasing upwards).
    """
    fig = Figure(figsize=(12, 5.5))
    ax_paths, ax_value = fig.subplots(1, 2)
    ax_paths.add_patch(_circle((0.0, 0.0), 2.0, "0.6", ":"))
    ax_paths.add_patch(_circle(target, switch_distance, "k", "--"))
    for path in effector_paths:
        xy = np.asarray(path)
        ax_paths.plot(xy[:, 0], xy[:, 1], linewidth=1.2)
        ax_paths.plot(xy[0, 0], xy[0, 1], marker="^", color="k", markersize=6)
    ax_paths.plot(*target, marker="*", color="gold", markersize=16, markeredgecolor="k")
    ax_paths.plot(0, 0, marker="o", color="k")
    ax_paths.set(
        xlim=(-2.1, 2.1),
        ylim=(-2.1, 2.1),
        aspect="equal",
        xlabel="x",
        ylabel="y",
        title="effector paths (dashed: switch to the fine stage)",
    )
    extent = (
        target[0] - half_width,
        target[0] + half_width,
        target[1] - half_width,
        target[1] + half_width,
    )
    image = ax_value.imshow(fine_values, origin="lower", extent=extent, cmap="viridis")
    ax_value.add_patch(_circle(target, switch_distance, "w", "--"))
    ax_value.plot(*target, marker="*", color="red", markersize=12)
    ax_value.set(xlabel="effector x", ylabel="effector y", title="fine stage V(s) near the target")
    fig.colorbar(image, ax=ax_value, label="V(s)")
    fig.tight_layout()
    return _save(fig, out)


ROBOT_COLORS = {"slider": "tab:blue", "propelled": "tab:orange"}


def plot_cargo_figure(
    occupancy: np.ndarray,
    trajectories: Sequence[tuple[Sequence[Sequence[float]], Sequence[int]]],
    *,
    robots: Sequence[str],
    stage_line: float,
    target: Sequence[float],
    success_radius: float,
    out: str | Path,
    title: str = "",
) -> Path:
    """The cargo-transport panel (paper's Fig. 3): obstacle map, stage line, target and example
    trajectories, each segment colored by the robot carrying the cargo.

    ``occupancy`` is the ``[H, W]`` obstacle map indexed ``[y, x]``; each trajectory is
    ``(positions [T+1, 2], stages [T+1])``.
    """
    height, width = occupancy.shape
    fig = Figure(figsize=(9, 6.8))
    ax = fig.subplots()
    ax.imshow(occupancy, origin="lower", extent=(0, width, 0, height), cmap="Greys", vmax=1.5)
    if len(robots) > 1:
        ax.axvline(stage_line, color="k", linestyle="--", linewidth=1.5)
    ax.add_patch(_circle(target, success_radius, "k", ":"))
    ax.plot(*target, marker="*", color="gold", markersize=18, markeredgecolor="k", zorder=5)
    for positions, stages in trajectories:
        xy, stage = np.asarray(positions), np.asarray(stages)
        for k, robot in enumerate(robots):
            # segments that start in stage k (their end point may already be in stage k + 1)
            idx = np.flatnonzero(stage[:-1] == k)
            for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                if len(run):
                    seg = xy[run[0] : run[-1] + 2]
                    ax.plot(seg[:, 0], seg[:, 1], color=ROBOT_COLORS.get(robot), linewidth=1.4)
        ax.plot(xy[0, 0], xy[0, 1], marker="o", color="k", markersize=5)
    for robot in robots:
        ax.plot([], [], color=ROBOT_COLORS.get(robot), label=f"{robot} robot")
    ax.legend(loc="lower right")
    ax.set(xlim=(0, width), ylim=(0, height), aspect="equal", xlabel="x (a)", ylabel="y (a)")
    ax.set_title(title or "cargo transport")
    fig.tight_layout()
    return _save(fig, out)


def _circle(center: Sequence[float], radius: float, color: str, style: str) -> Circle:
    return Circle(tuple(center), radius, fill=False, color=color, linestyle=style)
