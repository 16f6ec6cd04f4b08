"""The README's picture of SDQL: stacked stage learners and the transition reward.

python scripts/figure_sdql.py --out docs/sdql.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

STAGES = ("stage 0: get the key", "stage 1: open the door", "stage 2: reach the goal")
COLORS = ("#4C72B0", "#DD8452", "#55A868")


def draw(out: Path) -> None:
    fig, ax = plt.subplots(figsize=(10, 3.6))
    ax.set_xlim(0, 10)
    ax.set_ylim(0, 3.6)
    ax.axis("off")
    width, gap = 2.7, 0.55
    for k, (name, color) in enumerate(zip(STAGES, COLORS, strict=True)):
        x = 0.3 + k * (width + gap)
        ax.add_patch(
            FancyBboxPatch(
                (x, 2.0),
                width,
                1.2,
                boxstyle="round,pad=0.05",
                fc=color,
                alpha=0.18,
                ec=color,
                lw=1.5,
            )
        )
        ax.text(x + width / 2, 2.85, name, ha="center", va="center", fontsize=10)
        ax.text(
            x + width / 2,
            2.35,
            f"learner $Q_{k}$ (DQN, TD3, ...)",
            ha="center",
            va="center",
            fontsize=9,
        )
        # the states of a trajectory inside stage k
        xs = [x + 0.3 + i * (width - 0.6) / 3 for i in range(4)]
        ax.plot(xs, [1.2] * 4, "o-", color=color, ms=6)
        if k < len(STAGES) - 1:
            nx = 0.3 + (k + 1) * (width + gap) + 0.3
            ax.add_patch(
                FancyArrowPatch(
                    (xs[-1], 1.2),
                    (nx, 1.2),
                    arrowstyle="-|>",
                    mutation_scale=14,
                    color="black",
                    lw=1.5,
                )
            )
            ax.text((xs[-1] + nx) / 2, 0.75, f"leaves stage {k}", ha="center", fontsize=8)
            ax.text(
                (xs[-1] + nx) / 2,
                0.35,
                rf"$r_t + \gamma_{k}\, V_{k + 1}(s_{{t+1}})$",
                ha="center",
                fontsize=11,
            )
            # the value flows back from the next stage's learner (frozen in the backward schedule)
            ax.add_patch(
                FancyArrowPatch(
                    (nx + 0.5, 2.0),
                    (xs[-1] - 0.2, 2.0),
                    connectionstyle="arc3,rad=0.45",
                    arrowstyle="-|>",
                    mutation_scale=12,
                    color=COLORS[k + 1],
                    lw=1.2,
                    ls="--",
                )
            )
    ax.text(
        5,
        0.02,
        "stage k's learner: its own rewards, plus the next stage's value on the step "
        "that leaves stage k; trained last stage first (backward)",
        ha="center",
        fontsize=8.5,
        style="italic",
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/sdql.png"))
    draw(parser.parse_args().out)


if __name__ == "__main__":
    main()
