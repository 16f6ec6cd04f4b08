"""The grid world's figures (the paper's Fig. 2): greedy trajectories and the value map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from torchrl_stages.plots import save_figure

__all__ = ["plot_grid_trajectories", "plot_value_map"]


def _stage_boundaries(ax: Axes, n_cols: int, stage_width: int, color: str = "k") -> None:
    """Dashed lines between stages (cell edges lie at half-integers)."""
    for edge in range(stage_width, n_cols, stage_width):
        ax.axvline(edge - 0.5, color=color, linestyle="--", linewidth=1.5)


def _mark_target(ax: Axes, target: tuple[int, int], color: str = "gold") -> None:
    """A star on the target cell ``(row, col)``."""
    row, col = target
    ax.plot(
        col, row, "*", markersize=18, color=color, markeredgecolor="k", label="target", zorder=5
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
    """Paths of ``(row, col)`` cells over the grid (row 0 at the top), each starting at a ``^``,
    with a legend of ``labels`` (one per path) when given."""
    if labels is not None and len(labels) != len(paths):
        raise ValueError(f"got {len(labels)} labels for {len(paths)} paths")
    fig = Figure(figsize=(6.5, 6.5))
    ax = fig.add_subplot()
    ticks = np.arange(-0.5, size, 1.0)
    ax.set_xticks(ticks, minor=True)
    ax.set_yticks(ticks, minor=True)
    ax.grid(which="minor", color="0.85", linewidth=0.5)
    ax.tick_params(which="minor", length=0)
    ax.set(xlim=(-0.5, size - 0.5), ylim=(size - 0.5, -0.5), aspect="equal")  # row 0 on top
    ax.set(xlabel="column", ylabel="row")
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
        first = cells[0, 1], cells[0, 0]
        ax.plot(*first, "^", markersize=10, color=colors[i], markeredgecolor="k", zorder=4)
    _mark_target(ax, target)
    if title:
        ax.set_title(title, pad=22)
    if labels is not None and len(paths) > 0:
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    fig.tight_layout()
    return save_figure(fig, out)


def plot_value_map(
    values: np.ndarray,
    *,
    stage_width: int,
    target: tuple[int, int] | None = None,
    out: str | Path,
    title: str = "",
) -> Path:
    """Heat map of a ``(size, size)`` value array, row 0 at the top; non-finite entries blank."""
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
    ax.set(xlabel="column", ylabel="row")
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out)
