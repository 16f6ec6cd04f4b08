"""Figures in the style of the paper's Fig. 2: trajectories, value maps and learning curves.

Figures are built with :class:`matplotlib.figure.Figure` and written with ``savefig``, so no
pyplot state and no backend switching is involved: importing this module leaves the user's
matplotlib backend alone.
"""

from __future__ import annotations

import csv
import re
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import MaxNLocator

__all__ = [
    "plot_arm_figure",
    "plot_cargo_figure",
    "plot_grid_trajectories",
    "plot_learning_curves",
    "plot_value_map",
]

DPI = 120


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


#: per-stage rows of metrics.csv: train/stage_3/loss, eval/stage_3/success_rate and, under
#: the joint schedule, train/joint_1/episode_return, eval/joint_1/success_rate (phase 1)
_STAGE_METRIC = re.compile(
    r"^(?P<kind>train|eval)/(?P<scope>stage|joint)_(?P<stage>\d+)/(?P<metric>.+)$"
)
#: losses in the order their panels appear (others follow, sorted)
_LOSS_ORDER = ("loss", "loss_value", "loss_qvalue", "loss_actor")
Series = dict[tuple[str, str, str], list[tuple[float, float]]]  # (kind, scope, metric) -> points


def read_stage_metrics(metrics_csv: str | Path) -> dict[int, Series]:
    """``{stage: {(kind, scope, metric): [(step, value), ...]}}`` from a ``name,step,value``
    CSV (rows not tied to a stage, e.g. ``eval/task/...``, are left out)."""
    out: dict[int, Series] = defaultdict(lambda: defaultdict(list))
    with open(metrics_csv, newline="") as handle:
        for row in csv.DictReader(handle):
            match = _STAGE_METRIC.match(row.get("name") or "")
            if match is None:
                continue
            try:
                step, value = float(row["step"]), float(row["value"])
            except (KeyError, TypeError, ValueError):
                continue
            key = (match["kind"], match["scope"], match["metric"])
            out[int(match["stage"])][key].append((step, value))
    return out


def _stage_panels(series: Series, names: Sequence[str] | None) -> list[tuple[str, list]]:
    """The panels of one stage: every loss its learner logs (one each), its gradient norms,
    the evaluations' success and value error, and the training episode return."""
    metrics = {metric for (_, _, metric) in series if names is None or metric in names}
    keys = [k for k in series if k[2] in metrics]

    def pick(kind: str, test) -> list[tuple[str, str, str]]:
        return sorted(k for k in keys if k[0] == kind and test(k[2]))

    losses = sorted(
        {k[2] for k in pick("train", lambda m: m.startswith("loss"))},
        key=lambda m: (_LOSS_ORDER.index(m) if m in _LOSS_ORDER else len(_LOSS_ORDER), m),
    )
    panels = [(loss, pick("train", lambda m, loss=loss: m == loss)) for loss in losses]
    for title, kind, test in (
        ("gradient norm", "train", lambda m: m.startswith("grad_norm")),
        ("evaluation success rate", "eval", lambda m: m == "success_rate"),
        ("evaluation value error |V(s0) - G|", "eval", lambda m: m == "value_error"),
        ("training episode return", "train", lambda m: m == "episode_return"),
    ):
        chosen = pick(kind, test)
        if chosen:
            panels.append((title, chosen))
    return panels


def plot_learning_curves(
    metrics_csv: str | Path, out: str | Path, names: Sequence[str] | None = None
) -> Path | None:
    """Training curves of every stage: one row per stage, one panel per loss the stage's
    learner logs (DQN ``loss``; DDPG ``loss_value``, ``loss_actor``; TD3 ``loss_qvalue``,
    ``loss_actor``), its gradient norms (``grad_norm*``), the greedy evaluations' success rate
    and value error, and the training episode return, against the frames of the stage.

    Reads a ``name,step,value`` CSV (``train/stage_3/loss``, ``eval/stage_3/success_rate``;
    the joint schedule's ``eval/joint_<k>/...`` phase evaluations go to row k, dashed).
    ``names`` keeps only those metrics. Returns None when nothing matches.
    """
    stages = read_stage_metrics(metrics_csv)
    rows = [(k, _stage_panels(stages[k], names)) for k in sorted(stages)]
    rows = [(k, panels) for k, panels in rows if panels]
    if not rows:
        return None
    ncols = max(len(panels) for _, panels in rows)
    fig = Figure(figsize=(3.6 * ncols, 2.7 * len(rows) + 0.4))
    axes = fig.subplots(len(rows), ncols, squeeze=False)
    for r, (stage, panels) in enumerate(rows):
        series = stages[stage]
        for c in range(ncols):
            ax = axes[r, c]
            if c >= len(panels):
                ax.set_visible(False)
                continue
            title, keys = panels[c]
            for i, key in enumerate(keys):
                kind, scope, metric = key
                steps, vals = zip(*sorted(series[key]), strict=True)
                label = metric if scope == "stage" else f"{metric} (joint phase {stage})"
                ax.plot(
                    steps,
                    vals,
                    color=f"C{i % 10}",
                    label=label,
                    linestyle="-" if scope == "stage" else "--",
                    marker="o" if len(steps) == 1 or kind == "eval" else None,
                    markersize=3,
                )
            values = [v for key in keys for _, v in series[key]]
            if title == "evaluation success rate":
                ax.set_ylim(-0.05, 1.05)
            elif min(values) > 0 and max(values) > 20 * min(values):  # spans decades
                ax.set_yscale("log")
            ax.set_title(f"stage {stage}: {title}", fontsize=9)
            ax.set_xlabel("frames in stage", fontsize=8)
            ax.xaxis.set_major_locator(MaxNLocator(4))  # frame counts: few, readable ticks
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            if len(keys) > 1 or keys[0][1] != "stage":
                ax.legend(fontsize=7)
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
