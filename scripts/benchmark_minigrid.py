"""MiniGrid benchmark: the backward, joint and flat schedules on MiniGrid levels, seeds apart.

Each run is ``stages-train task=minigrid task.env.env_id=<level> schedule=<schedule>`` with the
task's defaults: a stage per goal of the level, of the same template, each with a budget of
``frames`` (300 000) and an early stop; the joint schedule's phases have the same budgets; the
flat learner gets their sum. The whole-task evaluation is 200 greedy episodes from the level's
own starts (a new layout each). Table: success, frames and training wall-clock per run;
``--jobs 2`` runs two at a time, one thread each (the wall-clock is then measured beside another
run, as under a sweep's joblib launcher). Rows accumulate in ``OUT/rows.json`` (a re-run
replaces its row), so runs launched apart, or side by side, make one table (``--table-only``
rewrites it from the rows).

    python scripts/benchmark_minigrid.py --levels MiniGrid-DoorKey-8x8-v0 --seeds 0 1 2 3 4 \
        --jobs 2 --out results/minigrid [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import fcntl
import json
import multiprocessing
import shutil
import statistics
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from _benchmark import add_table_argument, command_line, machine_speed, speed_note, train

from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS

SCHEDULES = ("backward", "joint", "flat")
#: the key that names a task's level
LEVEL_KEYS = {"minigrid": "task.env.env_id", "metaworld": "task.env.env_name"}


def run(
    level: str, schedule: str, seed: int, out: Path, overrides: list[str], task: str = "minigrid"
) -> dict:
    register_configs(ALGORITHMS)
    run_dir = out / f"{level}_{schedule}_seed{seed}"
    result = train(
        task,
        run_dir,
        f"{LEVEL_KEYS[task]}={level}",
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


def merge_rows(path: Path, new: list[dict]) -> list[dict]:
    """``new`` merged into the rows already in ``path`` (one row per level, schedule and
    seed; a re-run replaces its row), under a lock: runs launched apart share one table."""
    path.touch()
    with path.open("r+") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        text = handle.read()
        rows = {_key(r): r for r in (json.loads(text) if text.strip() else [])}
        rows.update({_key(r): r for r in new})
        merged = sorted(rows.values(), key=_key)
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps(merged, indent=2))
    return merged


def _key(row: dict) -> tuple:
    return (row["level"], SCHEDULES.index(row["schedule"]), row["seed"])


def write_table(rows: list[dict], path: Path) -> str:
    """The results table (one line per run, a summary per level and schedule, the commands
    and machine speeds the rows were measured with) as Markdown."""
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
    for level in dict.fromkeys(r["level"] for r in rows):
        for schedule in SCHEDULES:
            done = [r for r in rows if r["level"] == level and r["schedule"] == schedule]
            if not done:
                continue
            solved = sum(r["success"] >= 0.95 for r in done)
            mean = statistics.mean(r["success"] for r in done)
            notes.append(
                f"- {level} {schedule}: success mean {mean:.1%}"
                f" (lowest {min(r['success'] for r in done):.1%}), {solved}/{len(done)} seeds at "
                f">= 95%; frames median {statistics.median(r['frames'] for r in done):.0f}; "
                f"training median {statistics.median(r['seconds'] for r in done):.0f} s"
            )
    speeds = [r["machine_speed"] for r in rows if "machine_speed" in r]
    if speeds:
        notes.append(
            f"- machine speed {min(speeds):.2g}-{max(speeds):.2g} frames/s when the runs began; "
            f"up to {max(r.get('jobs', 1) for r in rows)} runs at a time, one torch thread each"
        )
    commands = sorted({r["command"] for r in rows if "command" in r})
    table = ["```text", *(f"$ {c}" for c in commands), "```", "", *header, *lines, "", *notes]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(table) + "\n")
    return "\n".join(table)


def main(
    task: str = "minigrid", level: str = "MiniGrid-DoorKey-8x8-v0", doc: str = __doc__
) -> None:
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--levels", nargs="+", default=[level])
    parser.add_argument("--schedules", nargs="+", default=list(SCHEDULES), choices=SCHEDULES)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path(f"results/{task}"))
    add_table_argument(parser)
    parser.add_argument(
        "--table-only", action="store_true", help="write the table of OUT/rows.json, run nothing"
    )
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.table_only:
        rows = json.loads((args.out / "rows.json").read_text())
        print(write_table(rows, args.table or args.out / "table.md"))
        return
    command = command_line()
    print(command, flush=True)
    speed = machine_speed()
    jobs = [(lv, sc, sd) for lv in args.levels for sc in args.schedules for sd in args.seeds]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.jobs, mp_context=context) as pool:
        futures = [pool.submit(run, *job, args.out, args.overrides, task) for job in jobs]
        for future in futures:
            row = {**future.result(), "machine_speed": speed, "command": command}
            row["jobs"] = args.jobs
            print(f"{row['level']} {row['schedule']} seed {row['seed']}: {row}", flush=True)
            rows = merge_rows(args.out / "rows.json", [row])
    print(speed_note(speed, machine_speed()))
    text = write_table(rows, args.out / "table.md")
    if args.table is not None:
        write_table(rows, args.table)
    print(text)


if __name__ == "__main__":
    main()
