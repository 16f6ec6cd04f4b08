"""Where a run's wall-clock goes: collection, replay sampling, update, target update, evaluation,
logging and checkpoints, per stage, with gradient updates and env frames per second.

It trains one run of a task (any Hydra overrides) and reads each stage's timing breakdown
(``StageResult.timing``); the target-network update, which happens inside each gradient step,
is timed apart. ``update`` is then the loss, backward and optimizer step alone; ``updates/s``
counts gradient steps per second of update and target update, ``frames/s`` env frames per
second of collection (policy, env step, storing).

    python scripts/profile_stage.py [OVERRIDE ...] --task gridworld [--compile off default]
        [--threads 1 2]

Every combination of ``--threads`` and ``--compile`` trains one run, with the same seed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import tempfile
import time
from pathlib import Path

import torch
from _benchmark import (
    add_table_argument,
    command_line,
    compose_config,
    machine_speed,
    save_table,
    speed_note,
)

from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS
from torchrl_stages.learners.ops import FusedSoftUpdate
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.seed_run import SeedRun

PHASES = ("collect", "sample", "update", "target_update", "evaluate", "log", "checkpoint")


def profile(task: str, compile: str, threads: int | None, overrides: list[str], out: Path) -> dict:
    """Trains one run; returns its per-stage breakdown."""
    per_stage: dict[int, float] = {}
    current = {"stage": None}
    step, begin = FusedSoftUpdate.step, SeedRun.begin

    def timed_step(self) -> None:
        start = time.perf_counter()
        step(self)
        stage = current["stage"]
        per_stage[stage] = per_stage.get(stage, 0.0) + time.perf_counter() - start

    FusedSoftUpdate.step = timed_step
    try:
        pinned = [] if threads is None else [f"threads={threads}"]
        cfg = compose_config(task, f"compile={compile}", *pinned, "eval.plots=false", *overrides)
        threads = int(cfg.threads)
        experiment = Experiment(cfg, out / f"{task}_threads{threads}_{compile}")

        def begin_hook(store: SeedRun, scope: int | str):  # whose target updates are timed
            current["stage"] = scope
            return begin(store, scope)

        SeedRun.begin = begin_hook
        start = time.perf_counter()
        [result] = experiment.run()
        total = time.perf_counter() - start
    finally:
        FusedSoftUpdate.step = step
        SeedRun.begin = begin
    rows = []
    for stage in result["training"]["stages"]:
        k, timing = stage["stage"], dict(stage["timing"])
        target = (
            per_stage.get(k, 0.0)
            if len(result["training"]["stages"]) > 1
            else sum(per_stage.values())
        )
        timing["target_update"] = target
        timing["update"] = timing.get("update", 0.0) - target
        row = {
            "task": task,
            "threads": threads,
            "compile": compile,
            "stage": k,
            "frames": stage["frames"],
            "updates": stage["updates"],
            "seconds": stage["seconds"],
            **{phase: timing.get(phase, 0.0) for phase in PHASES},
        }
        learn = row["update"] + row["target_update"]
        row["updates_per_s"] = stage["updates"] / learn if learn > 0 else None
        row["frames_per_s"] = stage["frames"] / row["collect"] if row["collect"] > 0 else None
        rows.append(row)
    return {
        "task": task,
        "threads": threads,
        "compile": compile,
        "total_seconds": total,
        "stages": rows,
        "success_rate": result["success_rate"],
        # the task report's scalar bars (the grid world's path length and value error, ...)
        "task_metrics": {
            k: v for k, v in result.get("task_metrics", {}).items() if isinstance(v, int | float)
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="gridworld")
    parser.add_argument(
        "--compile",
        nargs="+",
        default=["off"],
        help="torch.compile modes to compare (off, default, ...)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[None],
        help="torch thread counts to compare (default: the config's, i.e. the task's)",
    )
    parser.add_argument("--out", type=Path, default=None)
    add_table_argument(parser)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    misplaced = [mode for mode in args.compile if "=" in mode]
    if misplaced:  # --compile takes every word after it
        parser.error(f"{misplaced} are not compile modes: put Hydra overrides before --compile")
    register_configs(ALGORITHMS)
    out = args.out or Path(tempfile.mkdtemp(prefix="profile_"))
    out.mkdir(parents=True, exist_ok=True)
    command = command_line()
    print(f"{command}\ntorch {torch.__version__}, {os.cpu_count()} CPUs; runs in {out}")
    header = [
        "threads",
        "compile",
        "stage",
        "frames",
        "updates",
        "train (s)",
        *PHASES,
        "updates/s",
        "frames/s",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    runs, summaries = [], []
    speed = machine_speed()
    for threads, mode in itertools.product(args.threads, args.compile):
        run = profile(args.task, mode, threads, args.overrides, out)
        runs.append(run)
        for r in run["stages"]:
            cells = [
                str(run["threads"]),
                mode,
                str(r["stage"]),
                str(r["frames"]),
                str(r["updates"]),
                f"{r['seconds']:.1f}",
                *(f"{r[p]:.1f}" for p in PHASES),
                f"{r['updates_per_s']:.0f}" if r["updates_per_s"] else "-",
                f"{r['frames_per_s']:.0f}" if r["frames_per_s"] else "-",
            ]
            lines.append("| " + " | ".join(cells) + " |")
        print("\n".join(lines[-len(run["stages"]) :]), flush=True)
        summary = (
            f"- {args.task}, threads={run['threads']}, compile={mode}: "
            f"{run['total_seconds']:.1f} s in all (training, evaluation, figures), "
            f"success {run['success_rate']:.1%}"
        )
        if run["task_metrics"]:
            summary += "; " + ", ".join(
                f"{k}={v if isinstance(v, bool) else f'{v:.4g}'}"
                for k, v in run["task_metrics"].items()
            )
        summaries.append(summary)
        print(summary, flush=True)
    (out / "rows.json").write_text(json.dumps(runs, indent=2))
    note = speed_note(speed, machine_speed())
    print(note)
    table = ["```text", f"$ {command}", "```", "", *lines, "", *summaries, note]
    save_table(out, table, args.table)
    print(f"wrote {out / 'rows.json'} and {out / 'table.md'}")


if __name__ == "__main__":
    main()
