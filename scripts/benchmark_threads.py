"""Training time with one and two torch threads, on a quiet machine and beside a busy process.

A task's ``threads`` default was measured on a quiet machine; on a shared one, another process
may hold a core. This script trains each task's default configuration (its stages' budgets
capped by the overrides given, no other change) with ``threads=1`` and ``threads=2``, once
alone and once beside one busy process (a single-threaded spin loop, the stand-in for another
user's job), and reports the training wall-clock and what the busy process costs. Run it with
nothing else on the machine.

Example:
    python scripts/benchmark_threads.py --task manipulator --seeds 0 \
        task.stages.coarse.frames=10240 task.stages.fine.frames=10240
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _benchmark import parse_args, run_table, train

SPIN = "while True: pass"


def busy_process() -> subprocess.Popen:
    """One single-threaded process that keeps a core busy until it is killed."""
    return subprocess.Popen([sys.executable, "-c", SPIN])


def main() -> None:
    variants = [f"{t}/{load}" for t in (1, 2) for load in ("quiet", "busy")]
    args = parse_args(__doc__, variants, task="manipulator")
    quiet: dict[tuple[str, int, int], float] = {}

    def run_one(variant: str, seed: int) -> dict[str, Any]:
        threads, load = variant.split("/")
        run_dir = Path(args.out) / f"{args.task}_{threads}_{load}_seed{seed}"
        spinner = busy_process() if load == "busy" else None
        try:
            time.sleep(0.5 if spinner else 0.0)  # the spinner holds its core before we start
            result = train(
                args.task, run_dir, f"seed={seed}", f"threads={threads}", *args.overrides
            )
        finally:
            if spinner is not None:
                spinner.kill()
                spinner.wait()
        training = result["training"]
        seconds = float(training["seconds"])
        frames = sum(stage["frames"] for stage in training["stages"])
        key = (args.task, int(threads), seed)
        if load == "quiet":
            quiet[key] = seconds
        return {
            "task": args.task,
            "threads": int(threads),
            "load": load,
            "seed": seed,
            "train_s": seconds,
            "frames": frames,
            "frames_per_s": frames / seconds,
            "vs_quiet": seconds / quiet[key] if key in quiet else None,
            "success_rate": result["success_rate"],
        }

    def cells(row: dict[str, Any]) -> list[str]:
        ratio = "" if row["vs_quiet"] is None else f"{row['vs_quiet']:.2f}x"
        return [
            row["task"],
            str(row["threads"]),
            row["load"],
            str(row["seed"]),
            f"{row['train_s']:.1f}",
            f"{row['frames']:,}".replace(",", " "),
            f"{row['frames_per_s']:.0f}",
            ratio,
        ]

    columns = ["task", "threads", "load", "seed", "train s", "frames", "frames/s", "vs quiet"]
    run_table(args, columns, run_one, cells)


if __name__ == "__main__":
    main()
