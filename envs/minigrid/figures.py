"""The MiniGrid task's figure: a level with the greedy stacked policy's path, colored by stage."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from torchrl_stages.plots import save_figure

from .._common import stage_segments

__all__ = ["STAGE_COLORS", "plot_level"]

STAGE_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")


def plot_level(
    frame: np.ndarray,
    positions: Sequence[Sequence[int]],
    stages: Sequence[int],
    *,
    stage_names: Sequence[str],
    tile: int,
    out: str | Path,
    title: str = "",
) -> Path:
    """The level's picture ``frame`` (``[H, W, 3]``, ``tile`` pixels per cell) with the path
    through the cells ``positions [T+1, 2]``, colored by stage, and a star where each ends."""
    xy = (np.asarray(positions, dtype=float) + 0.5) * tile
    stage = np.asarray(stages)
    fig = Figure(figsize=(6, 6 * frame.shape[0] / frame.shape[1] + 0.4))
    ax = fig.subplots()
    ax.imshow(frame)
    for k, name in enumerate(stage_names):
        for seg in stage_segments(xy, stage, k):
            ax.plot(
                seg[:, 0],
                seg[:, 1],
                color=STAGE_COLORS[k % len(STAGE_COLORS)],
                linewidth=3,
                alpha=0.85,
            )
        ax.plot(
            [],
            [],
            color=STAGE_COLORS[k % len(STAGE_COLORS)],
            linewidth=3,
            label=f"stage {k}: {name}",
        )
    ax.plot(*xy[0], marker="o", color="white", markeredgecolor="k", markersize=9)
    for t in np.flatnonzero(np.diff(stage)) + 1:  # where each stage ends (key, door)
        color = STAGE_COLORS[int(stage[t - 1]) % len(STAGE_COLORS)]
        ax.plot(*xy[t], marker="*", color=color, markeredgecolor="white", markersize=16)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=len(stage_names), fontsize=8)
    ax.set_axis_off()
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, out)
