"""The manipulator's figure (the paper's Fig. 4(b)): effector paths and the fine stage's value."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from torchrl_stages.plots import circle, save_figure

__all__ = ["plot_arm_figure"]


def plot_arm_figure(
    effector_paths: Sequence[Sequence[Sequence[float]]],
    fine_values: np.ndarray,
    *,
    target: Sequence[float],
    half_width: float,
    switch_distance: float,
    out: str | Path,
) -> Path:
    """Effector paths, and the fine stage's value ``fine_values``, an ``n x n`` map of effector
    positions within ``half_width`` of the target (x along columns, y upwards)."""
    fig = Figure(figsize=(12, 5.5))
    ax_paths, ax_value = fig.subplots(1, 2)
    ax_paths.add_patch(circle((0.0, 0.0), 2.0, "0.6", ":"))
    ax_paths.add_patch(circle(target, switch_distance, "k", "--"))
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
    ax_value.add_patch(circle(target, switch_distance, "w", "--"))
    ax_value.plot(*target, marker="*", color="red", markersize=12)
    ax_value.set(xlabel="effector x", ylabel="effector y", title="fine stage V(s) near the target")
    fig.colorbar(image, ax=ax_value, label="V(s)")
    fig.tight_layout()
    return save_figure(fig, out)
