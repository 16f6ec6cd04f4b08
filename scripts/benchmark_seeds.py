"""Many seeds in one process (``stages-train seeds=[...]``) against the same seeds run apart.

Three measurements, each a table in ``OUT/table.md``:

``--quality`` (no wall-clock: it may run beside other work): the grid world's discount
presets (``homo``, ``hetero``) with ``seeds=[...]`` in one process, every seed's run checked
against the bars of ``benchmark_gridworld.py`` (success from every start, optimal path, value
error <= 0.05), and ``--manipulator``: the manipulator's seeds the same way (success over its
whole-task episodes; ``--manipulator-experiment manipulator_td3``: with that experiment's TD3
stages).

``--timing``: one sweep of ``--seeds`` on the grid world (default config), wall-clock of the
whole command from launch to exit, in four ways, each ``--repeats`` times, alternated:
  vectorized     stages-train seeds=[...] threads=1
  vectorized-2t  stages-train seeds=[...] threads=2
  sequential     stages-train -m seed=... threads=1 (Hydra's basic launcher: one job after another)
  joblib         stages-train -m seed=... threads=1 hydra/launcher=joblib, 2 jobs at a time
with each command's largest resident memory (for the vectorized ones: all seeds in one process;
``--memory`` adds a one-seed vectorized run, so that the memory a seed adds can be read off).

    python scripts/benchmark_seeds.py --quality --seeds 0 1 2 ... 19 --out results/seeds_q
    python scripts/benchmark_seeds.py --timing --seeds 0 1 ... 9 --memory --out results/seeds_t
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _benchmark import add_table_argument, command_line, machine_speed, save_table, speed_note
from benchmark_gridworld import VARIANTS, grid_row

WAYS = ("vectorized", "vectorized-2t", "sequential", "joblib")


def stages_train() -> str:
    return str(Path(sys.executable).parent / "stages-train")


def timed(argv: list[str], log: Path) -> tuple[float, float]:
    """Runs ``argv`` to completion: its wall-clock (s) and largest resident memory (MiB, of the
    process or of any of its children, e.g. joblib's workers)."""
    start = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(argv)} failed (exit {status}); see {log}")
    return seconds, usage.ru_maxrss / 1024


def sweep_argv(way: str, seeds: list[int], out: Path) -> list[str]:
    listed = ",".join(str(s) for s in seeds)
    common = ["eval.plots=false", "progress=false"]
    if way.startswith("vectorized"):
        threads = 2 if way.endswith("2t") else 1
        return [
            stages_train(),
            f"seeds=[{listed}]",
            f"threads={threads}",
            f"hydra.run.dir={out}",
            *common,
        ]
    launcher = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"] if way == "joblib" else []
    return [
        stages_train(),
        "-m",
        f"seed={listed}",
        "threads=1",
        *launcher,
        f"hydra.sweep.dir={out}",
        *common,
    ]


def seed_results(run_dir: Path, seeds: list[int]) -> list[dict]:
    return [json.loads((run_dir / f"seed_{s}" / "eval.json").read_text()) for s in seeds]


def quality(args: argparse.Namespace) -> list[str]:
    lines = ["| task / preset | seeds | pass | max abs V error (median, max) | frames per seed |"]
    lines.append("|---|---|---|---|---|")
    notes = []
    for variant in args.variants:
        run_dir = args.out / f"quality_{variant}"
        listed = ",".join(str(s) for s in args.seeds)
        argv = [stages_train(), f"seeds=[{listed}]", *VARIANTS[variant], f"hydra.run.dir={run_dir}"]
        timed([*argv, "eval.plots=false", "progress=false"], run_dir.with_suffix(".log"))
        results = seed_results(run_dir, args.seeds)
        rows = [grid_row(variant, s, r) for s, r in zip(args.seeds, results, strict=True)]
        errors = [r["value_error"] for r in rows]
        frames = [r["frames"] for r in rows]
        failed = [r["seed"] for r in rows if not r["pass"]]
        lines.append(
            f"| grid world / {variant} | {args.seeds[0]}-{args.seeds[-1]} | "
            f"{len(rows) - len(failed)}/{len(rows)} | {statistics.median(errors):.3f}, "
            f"{max(errors):.3f} | median {statistics.median(frames):.0f} |"
        )
        if failed:
            notes.append(f"- grid world / {variant}: seeds that fail a bar: {failed}")
    if args.manipulator:
        experiment = args.manipulator_experiment
        run_dir = args.out / f"quality_{experiment or 'manipulator'}"
        seeds = args.manipulator
        task = f"experiment={experiment}" if experiment else "task=manipulator"
        argv = [stages_train(), task, f"seeds=[{','.join(map(str, seeds))}]"]
        argv += [f"hydra.run.dir={run_dir}", "eval.plots=false", "progress=false"]
        timed(argv, run_dir.with_suffix(".log"))
        results = seed_results(run_dir, seeds)
        rates = [r["success_rate"] for r in results]
        frames = [sum(st["frames"] for st in r["training"]["stages"]) for r in results]
        name = f"manipulator ({experiment})" if experiment else "manipulator"
        lines.append(
            f"| {name} | {seeds[0]}-{seeds[-1]} | {sum(x >= 0.95 for x in rates)}/"
            f"{len(rates)} at >= 95% success ({', '.join(f'{x:.1%}' for x in rates)}) | - | "
            f"median {statistics.median(frames):.0f} |"
        )
    return [*lines, "", *notes]


def timing(args: argparse.Namespace) -> list[str]:
    measured: dict[str, list[tuple[float, float]]] = {way: [] for way in WAYS}
    for rep in range(args.repeats):
        order = WAYS if rep % 2 == 0 else tuple(reversed(WAYS))
        for way in order:
            out = args.out / f"timing_{way}_{rep}"
            seconds, rss = timed(sweep_argv(way, args.seeds, out), out.with_suffix(".log"))
            measured[way].append((seconds, rss))
            print(f"{way} (repeat {rep}): {seconds:.1f} s, {rss:.0f} MiB", flush=True)
    base = statistics.median(s for s, _ in measured["sequential"])
    lines = [
        f"| {len(args.seeds)} grid-world seeds, launched as | wall-clock (s), each repeat | "
        "median | vs sequential | largest resident memory (MiB) |",
        "|---|---|---|---|---|",
    ]
    for way in WAYS:
        secs = [s for s, _ in measured[way]]
        med = statistics.median(secs)
        lines.append(
            f"| {way} | {', '.join(f'{s:.1f}' for s in secs)} | {med:.1f} | "
            f"{base / med:.2f}x | {max(r for _, r in measured[way]):.0f} |"
        )
    notes = []
    if args.memory:
        one = args.out / "memory_one_seed"
        _, rss_one = timed(sweep_argv("vectorized", args.seeds[:1], one), one.with_suffix(".log"))
        rss_all = max(r for _, r in measured["vectorized"])
        per_seed = (rss_all - rss_one) / max(len(args.seeds) - 1, 1)
        notes.append(
            f"- memory: one seed in one process {rss_one:.0f} MiB, {len(args.seeds)} seeds "
            f"{rss_all:.0f} MiB: {per_seed:.1f} MiB per added seed"
        )
    return [*lines, "", *notes]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--quality", action="store_true")
    parser.add_argument("--variants", nargs="*", default=["homo", "hetero"], choices=list(VARIANTS))
    parser.add_argument("--manipulator", type=int, nargs="*", default=[], help="its seeds")
    parser.add_argument(
        "--manipulator-experiment",
        default="",
        help="train the manipulator's seeds with experiment=<this> (e.g. manipulator_td3)",
    )
    parser.add_argument("--timing", action="store_true")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--memory", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    add_table_argument(parser)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    speed = machine_speed()
    table = [f"```text\n$ {command_line()}\n```", ""]
    if args.quality:
        table += quality(args)
    if args.timing:
        table += ["", *timing(args)] if args.quality else timing(args)
    table.append(speed_note(speed, machine_speed()))
    table.append(f"- {os.cpu_count()} CPUs")
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
