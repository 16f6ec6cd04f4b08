"""MiniGrid's schedules in one figure: each run's whole-task success against the frames it
trained, per level and schedule (every seed a dot; the median a larger mark, its bars the
spread over seeds), read from the tables ``benchmark_minigrid.py`` wrote.

    python scripts/figure_minigrid.py --out docs/minigrid_schedules.png docs/tables/minigrid_*.md
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from pathlib import Path

from matplotlib.figure import Figure

SCHEDULES = ("backward", "joint", "flat")
Runs = dict[str, dict[str, list[tuple[int, float]]]]  # level -> schedule -> (frames, success)


def read_runs(tables: list[Path]) -> Runs:
    """The rows of ``benchmark_minigrid.py``'s tables (``| level | schedule | seed | success |
    frames | ...``), a level and schedule's seeds gathered over the tables."""
    runs: Runs = defaultdict(lambda: defaultdict(list))
    for table in tables:
        for line in table.read_text().splitlines():
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) >= 5 and cells[0].startswith("MiniGrid-") and cells[1] in SCHEDULES:
                success = float(cells[3].removesuffix("%")) / 100
                runs[cells[0]][cells[1]].append((int(cells[4]), success))
    return runs


def plot(runs: Runs, out: Path) -> Path:
    """One panel per level: success (%) against frames (millions), per schedule."""
    levels = sorted(runs)
    fig = Figure(figsize=(3.4 * len(levels), 3.4))
    axes = fig.subplots(1, len(levels), squeeze=False)[0]
    for ax, level in zip(axes, levels, strict=True):
        for i, schedule in enumerate(SCHEDULES):
            points = runs[level].get(schedule, [])
            if not points:
                continue
            frames = [f / 1e6 for f, _ in points]
            success = [100 * s for _, s in points]
            color = f"C{i}"
            ax.scatter(frames, success, s=12, color=color, alpha=0.45)
            mid = (statistics.median(frames), statistics.median(success))
            spread_x = [[mid[0] - min(frames)], [max(frames) - mid[0]]]
            spread_y = [[mid[1] - min(success)], [max(success) - mid[1]]]
            ax.errorbar(*mid, xerr=spread_x, yerr=spread_y, fmt="o", ms=7, color=color, capsize=3)
            ax.plot([], [], "o", color=color, label=f"{schedule} ({len(points)} seeds)")
        ax.set_title(level.removeprefix("MiniGrid-").removesuffix("-v0"), fontsize=10)
        ax.set(xlabel="frames trained (millions)", ylim=(-5, 105))
        ax.set_xlim(left=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="center right")
    axes[0].set_ylabel("whole-task success (%)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", type=Path, nargs="+", help="benchmark_minigrid.py's tables")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args()
    runs = read_runs(args.tables)
    if not runs:
        raise SystemExit(f"error: no MiniGrid run in {', '.join(map(str, args.tables))}")
    print(f"wrote {plot(runs, args.out)}")


if __name__ == "__main__":
    main()
