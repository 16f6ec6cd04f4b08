"""Schedules benchmark: backward vs joint (the paper's Algorithm 1) vs flat on every task.

Each run follows the whole task while it trains (``eval.probe=true``): at every evaluation of
stage 0 (backward), of phase 0 (joint) or of the flat learner, the greedy whole-task success
(and, on the grid world, whether the greedy path from (0, 0) is optimal and the merged value
error against dynamic programming) is logged against the frames of all stages so far. The table
reports the final whole-task success, the frames and wall-clock to the first optimal path from
(0, 0) (grid world), the final merged value error, and the frames and training wall-clock; the
figure ``schedules_<task>.png`` plots the followed numbers against frames per schedule (the
median over seeds, its band from the lowest to the highest seed); ``--figures DIR`` writes a
copy there too (``../docs``, beside the table the docs include).

Tasks: gridworld-homo, gridworld-hetero, manipulator, cargo. The flat baseline is one learner
over the whole task; cargo's stages act on different action entries, so its flat run is the
self-propelled robot alone for the whole trip.

    python scripts/benchmark_schedules.py --seeds 0 1 2 \
        --variants gridworld-homo/backward gridworld-homo/joint gridworld-homo/flat [OVERRIDE]
"""

from __future__ import annotations

import argparse
import csv
import shutil
import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np
from _benchmark import parse_args, run_table, train
from matplotlib.figure import Figure

from torchrl_stages.metric_names import TASK, parse_metric

TASKS = {
    "gridworld-homo": ("gridworld", ["task/gammas=homo"]),
    "gridworld-hetero": ("gridworld", ["task/gammas=hetero"]),
    "manipulator": ("manipulator", []),
    "cargo": ("cargo", []),
}
SCHEDULES = ("backward", "joint", "flat")
# the flat baseline's own settings: cargo's is the self-propelled robot alone; the grid world's
# one network over the whole task learns at 2e-3 with 64 envs, so that its exploration anneals
# over whole-task episodes (docs/results/schedules.md has the measurements behind both)
FLAT = {
    "cargo": ["task.env.robots=[propelled]", "~task.stages.slider"],
    "gridworld": ["task.stages.s0.lr=2e-3", "task.stages.s0.num_envs=64"],
}


def curves(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """The probe's ``eval/task/*`` series of a run, by metric."""
    series: dict[str, list[tuple[int, float]]] = defaultdict(list)
    with (run_dir / "metrics.csv").open() as f:
        for row in csv.DictReader(f):
            name = parse_metric(row["name"])
            if name is not None and name.scope == TASK:
                series[name.metric].append((int(row["step"]), float(row["value"])))
    return series


def run(variant: str, seed: int, out: Path, extra: list[str]) -> dict:
    name, schedule = variant.split("/")
    task, overrides = TASKS[name]
    if schedule == "flat":
        overrides = [*overrides, *FLAT.get(task, [])]
    run_dir = out / f"{name}_{schedule}_seed{seed}"
    result = train(
        task, run_dir, f"seed={seed}", f"schedule={schedule}", "eval.probe=true", *overrides, *extra
    )
    series = curves(run_dir)
    first = next((step for step, v in series.get("path_optimal", []) if v == 1.0), None)
    seconds = dict(series.get("seconds", []))
    metrics = result.get("task_metrics", {})
    return {
        "variant": variant,
        "task": name,
        "schedule": schedule,
        "seed": seed,
        "success": result["success_rate"],
        "frames_to_optimal_path": first,
        "seconds_to_optimal_path": seconds.get(first),
        "value_error": metrics.get("value_map_max_abs_error"),
        "optimal_path": metrics.get("path_from_origin_optimal"),
        "frames": sum(s["frames"] for s in result["training"]["stages"]),
        "seconds": result["training"]["seconds"],
        "curves": series,
    }


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def plot(rows: list[dict], out: Path) -> list[Path]:
    """One figure per task: the followed numbers against frames, per schedule (the median over
    seeds; the band, the lowest to the highest seed)."""
    paths = []
    for task in dict.fromkeys(r["task"] for r in rows):
        done = [r for r in rows if r["task"] == task]
        metrics = [m for m in ("success_rate", "value_error") if done[0]["curves"].get(m)]
        fig = Figure(figsize=(6.5 * len(metrics), 4.2))
        axes = fig.subplots(1, len(metrics), squeeze=False)[0]
        for ax, metric in zip(axes, metrics, strict=True):
            for i, schedule in enumerate(SCHEDULES):
                runs = [r["curves"][metric] for r in done if r["schedule"] == schedule]
                if not runs:
                    continue
                grid = np.unique(np.concatenate([[s for s, _ in c] for c in runs]))
                # each seed's last value so far at every frame count (nan before its first)
                ys = np.array(
                    [
                        np.interp(grid, *zip(*c, strict=True), left=np.nan)
                        if len(c) > 1
                        else np.where(grid >= c[0][0], c[0][1], np.nan)
                        for c in runs
                    ]
                )
                label = f"{schedule}: median of {len(runs)} seeds"
                z = len(SCHEDULES) - i  # the stacked schedules' short curves drawn on top
                median = np.nanmedian(ys, 0)
                ax.plot(grid, median, ".-", ms=5, lw=2, color=f"C{i}", label=label, zorder=z + 3)
                low, high = np.nanmin(ys, 0), np.nanmax(ys, 0)
                ax.fill_between(grid, low, high, color=f"C{i}", alpha=0.2, zorder=z)
            ax.set(xlabel="frames (all stages)", ylabel=metric, title=f"{task}: {metric}")
            if metric == "value_error":
                ax.set_yscale("log")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"schedules_{task}.png"
        fig.savefig(path, dpi=110)
        paths.append(path)
    return paths


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        done = [r for r in rows if r["variant"] == variant]
        line = (
            f"- {variant}: success mean {statistics.mean(r['success'] for r in done):.1%} "
            f"(lowest {min(r['success'] for r in done):.1%}); training median "
            f"{statistics.median(r['seconds'] for r in done):.0f} s"
        )
        reached = [r["frames_to_optimal_path"] for r in done if r["frames_to_optimal_path"]]
        if done[0]["value_error"] is not None:
            line += (
                f"; optimal path in {len(reached)}/{len(done)} runs"
                + (
                    f", first after a median {statistics.median(reached):.0f} frames"
                    if reached
                    else ""
                )
                + f"; value error max {max(r['value_error'] for r in done):.3f}"
            )
        lines.append(line)
    return lines


def main() -> None:
    variants = [f"{t}/{s}" for t in TASKS for s in SCHEDULES]
    args: argparse.Namespace = parse_args(__doc__, variants, figures="")  # e.g. ../docs
    columns = ["task / schedule", "seed", "success", "frames to optimal path"]
    columns += ["wall-clock to optimal path (s)", "max abs V error", "frames", "train (s)"]
    rows = run_table(
        args,
        columns,
        lambda variant, seed: run(variant, seed, args.out, args.overrides),
        lambda r: [
            r["variant"],
            str(r["seed"]),
            f"{r['success']:.1%}",
            _fmt(r["frames_to_optimal_path"], "d"),
            _fmt(r["seconds_to_optimal_path"], ".1f"),
            _fmt(r["value_error"], ".3f"),
            str(r["frames"]),
            f"{r['seconds']:.0f}",
        ],
        summary,
    )
    for path in plot(rows, args.out):
        print(f"wrote {path}")
        if args.figures:
            copy = Path(args.figures) / path.name
            copy.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, copy)
            print(f"wrote {copy}")


if __name__ == "__main__":
    main()
