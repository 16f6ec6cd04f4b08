"""MiniGrid benchmark: the backward, joint and flat schedules on MiniGrid levels, seeds apart.

Each run is ``stages-train task=minigrid task.env.env_id=<level> schedule=<schedule>`` with the
task's defaults: three stages of the same template, each with a budget of ``frames`` (300 000)
and an early stop; the joint schedule's phases have the same budgets; the flat learner gets
their sum. The whole-task evaluation is 200 greedy episodes from the level's own starts (a new
layout each). Table: success, frames and training wall-clock per run; ``--jobs 2`` runs two at a
time, one thread each (the wall-clock is then measured beside another run, as under a sweep's
joblib launcher).

    python scripts/benchmark_minigrid.py --levels MiniGrid-DoorKey-8x8-v0 --seeds 0 1 2 3 4 \
        --jobs 2 --out results/minigrid [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import shutil
import statistics
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from _benchmark import command_line, machine_speed, speed_note, train

from torchrl_stages.store import register_configs

SCHEDULES = ("backward", "joint", "flat")


def run(level: str, schedule: str, seed: int, out: Path, overrides: list[str]) -> dict:
    register_configs()
    run_dir = out / f"{level}_{schedule}_seed{seed}"
    result = train(
        "minigrid",
        run_dir,
        f"task.env.env_id={level}",
        f"schedule={schedule}",
        f"seed={seed}",
        "threads=1",
        *overrides,
    )
    if (run_dir / "minigrid.png").is_file():  # one figure per level and schedule, for the docs
        shutil.copy(run_dir / "minigrid.png", out / f"minigrid_{level}_{schedule}_seed{seed}.png")
    return {
        "level": level,
        "schedule": schedule,
        "seed": seed,
        "success": result["success_rate"],
        "episodes": result["episodes"],
        "mean_steps": result["mean_steps"],
        "frames": sum(s["frames"] for s in result["training"]["stages"]),
        "seconds": result["training"]["seconds"],
        "stage_frames": [s["frames"] for s in result["training"]["stages"]],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--levels", nargs="+", default=["MiniGrid-DoorKey-8x8-v0"])
    parser.add_argument("--schedules", nargs="+", default=list(SCHEDULES), choices=SCHEDULES)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("results/minigrid"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    command = command_line()
    print(command, flush=True)
    speed = machine_speed()
    jobs = [(lv, sc, sd) for lv in args.levels for sc in args.schedules for sd in args.seeds]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        futures = [pool.submit(run, *job, args.out, args.overrides) for job in jobs]
        rows = []
        for future in futures:
            rows.append(future.result())
            row = rows[-1]
            print(f"{row['level']} {row['schedule']} seed {row['seed']}: {row}", flush=True)
            (args.out / "rows.json").write_text(json.dumps(rows, indent=2))
    header = [
        "| level | schedule | seed | success | frames | train (s) |",
        "|---|---|---|---|---|---|",
    ]
    lines = [
        f"| {r['level']} | {r['schedule']} | {r['seed']} | {r['success']:.1%} | {r['frames']} | "
        f"{r['seconds']:.0f} |"
        for r in rows
    ]
    notes = []
    for level in args.levels:
        for schedule in args.schedules:
            done = [r for r in rows if r["level"] == level and r["schedule"] == schedule]
            solved = sum(r["success"] >= 0.95 for r in done)
            mean = statistics.mean(r["success"] for r in done)
            notes.append(
                f"- {level} {schedule}: success mean {mean:.1%}"
                f" (lowest {min(r['success'] for r in done):.1%}), {solved}/{len(done)} seeds at "
                f">= 95%; frames median {statistics.median(r['frames'] for r in done):.0f}; "
                f"training median {statistics.median(r['seconds'] for r in done):.0f} s"
            )
    notes.append(f"- {args.jobs} run(s) at a time, one torch thread each")
    notes.append(speed_note(speed, machine_speed()))
    table = ["```text", f"$ {command}", "```", "", *header, *lines, "", *notes]
    (args.out / "table.md").write_text("\n".join(table) + "\n")
    print("\n".join(table))


if __name__ == "__main__":
    main()
