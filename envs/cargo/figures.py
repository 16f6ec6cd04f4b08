"""The cargo task's figure (the paper's Fig. 3): the map, the stage line and trajectories."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from torchrl_stages.plots import circle, save_figure

from .._common import stage_segments

__all__ = ["ROBOT_COLORS", "plot_cargo_figure"]


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
    """The obstacle map ``[H, W]`` (indexed ``[y, x]``), stage line, target and trajectories
    ``(positions [T+1, 2], stages [T+1])``, each step colored by the robot carrying the cargo."""
    height, width = occupancy.shape
    fig = Figure(figsize=(9, 6.8))
    ax = fig.subplots()
    ax.imshow(occupancy, origin="lower", extent=(0, width, 0, height), cmap="Greys", vmax=1.5)
    if len(robots) > 1:
        ax.axvline(stage_line, color="k", linestyle="--", linewidth=1.5)
    ax.add_patch(circle(target, success_radius, "k", ":"))
    ax.plot(*target, marker="*", color="gold", markersize=18, markeredgecolor="k", zorder=5)
    for positions, stages in trajectories:
        xy, stage = np.asarray(positions), np.asarray(stages)
        for k, robot in enumerate(robots):
            for seg in stage_segments(xy, stage, k):
                ax.plot(seg[:, 0], seg[:, 1], color=ROBOT_COLORS.get(robot), linewidth=1.4)
        ax.plot(xy[0, 0], xy[0, 1], marker="o", color="k", markersize=5)
    for robot in robots:
        ax.plot([], [], color=ROBOT_COLORS.get(robot), label=f"{robot} robot")
    ax.legend(loc="lower right")
    ax.set(xlim=(0, width), ylim=(0, height), aspect="equal", xlabel="x (a)", ylabel="y (a)")
    ax.set_title(title or "cargo transport")
    fig.tight_layout()
    return save_figure(fig, out)
