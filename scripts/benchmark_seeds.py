"""Many seeds in one process (``stages-train seeds=[...]``) against the same seeds run apart.

Four measurements, each a table in ``OUT/table.md``:

``--quality`` (no wall-clock: it may run beside other work): the grid world's discount
presets (``homo``, ``hetero``) with ``seeds=[...]`` in one process, every seed's run checked
against the bars of ``benchmark_gridworld.py`` (success from every start, optimal path, value
error <= 0.05) (``--schedule joint|flat``: that schedule's; ``--apart``: also each seed in a run
of its own, one after another, the same bars; for every task), and ``--manipulator``: the
manipulator's seeds the same way (success over its whole-task episodes; ``--manipulator-experiment
manipulator_td3``: with that experiment's TD3 stages, ``--manipulator-algo sac``: both stages
with that algorithm), ``--cargo``: cargo's seeds the same way.

``--timing``: one sweep of ``--seeds`` on the grid world (default config), wall-clock of the
whole command from launch to exit, in four ways, each ``--repeats`` times, alternated:
  vectorized     stages-train seeds=[...] threads=1
  vectorized-2t  stages-train seeds=[...] threads=2
  sequential     stages-train -m seed=... threads=1 (Hydra's basic launcher: one job after another)
  joblib         stages-train -m seed=... threads=1 hydra/launcher=joblib, --jobs at a time (2)
with each command's largest resident memory (for the vectorized ones: all seeds in one process;
``--memory`` adds a one-seed vectorized run, so that the memory a seed adds can be read off).

``--scaling 1 10 100`` (on a GPU: ``--device cuda``): the grid world's first 1, 10, 100 seeds
vectorized on ``--device``, one launch each, its wall-clock, every seed checked against the
bars of ``--quality``, the largest resident memory and (on a GPU) the GPU's largest memory in
use; with, as the sequential reference, one seed on this machine's CPU (``threads=1``).

    python scripts/benchmark_seeds.py --quality --seeds 0 1 2 ... 19 --out results/seeds_q
    python scripts/benchmark_seeds.py --timing --seeds 0 1 ... 9 --memory --out results/seeds_t
    python scripts/benchmark_seeds.py --scaling 1 10 100 --device cuda --out results/seeds_gpu
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from _benchmark import add_table_argument, command_line, machine_speed, save_table, speed_note
from benchmark_gridworld import VARIANTS, grid_row

WAYS = ("vectorized", "vectorized-2t", "sequential", "joblib")


def stages_train() -> str:
    """The ``stages-train`` console script beside this interpreter, else on ``PATH`` (a
    package installed with ``pip install --target``)."""
    beside = Path(sys.executable).parent / "stages-train"
    return str(beside) if beside.exists() else shutil.which("stages-train") or str(beside)


class GPUMemory:
    """The GPUs' largest memory in use (MiB, ``nvidia-smi``, read every 0.2 s) while the
    ``with`` block runs; ``None`` without ``nvidia-smi``."""

    def __enter__(self) -> GPUMemory:
        self.peak: float | None = None
        self._stop = threading.Event()
        self._thread = None
        if shutil.which("nvidia-smi"):
            self._thread = threading.Thread(target=self._poll, daemon=True)
            self._thread.start()
        return self

    def _poll(self) -> None:
        query = ["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"]
        while not self._stop.wait(0.2):
            out = subprocess.run(query, capture_output=True, text=True, check=False).stdout
            used = [float(x) for x in out.split() if x.replace(".", "", 1).isdigit()]
            if used:
                self.peak = max(self.peak or 0.0, sum(used))

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


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


def sweep_argv(
    way: str, seeds: list[int], out: Path, jobs: int = 2, overrides: Sequence[str] = ()
) -> list[str]:
    listed = ",".join(str(s) for s in seeds)
    common = ["eval.plots=false", "progress=false", *overrides]
    if way.startswith("vectorized"):
        threads = 2 if way.endswith("2t") else 1
        return [
            stages_train(),
            f"seeds=[{listed}]",
            f"threads={threads}",
            f"hydra.run.dir={out}",
            *common,
        ]
    launcher = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"] if way == "joblib" else []
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


def ways(args: argparse.Namespace) -> list[str]:
    """How ``--quality`` trains the seeds: in one process, and with ``--apart`` also apart."""
    return ["in one process", "apart"] if args.apart else ["in one process"]


def train_seeds(way: str, overrides: list[str], seeds: list[int], run: Path) -> list[dict]:
    """Trains ``seeds`` of one config (``overrides``) in one process (``seeds=[...]``, seed s in
    ``run/seed_s``) or ``"apart"`` (Hydra's basic launcher: one job after another, job i in
    ``run_i/i``); returns each seed's ``eval.json``."""
    listed = ",".join(map(str, seeds))
    if way == "apart":
        run = run.with_name(f"{run.name}_apart")
        argv = [stages_train(), "-m", *overrides, f"seed={listed}", f"hydra.sweep.dir={run}"]
        dirs = [run / str(i) for i in range(len(seeds))]
    else:
        argv = [stages_train(), *overrides, f"seeds=[{listed}]", f"hydra.run.dir={run}"]
        dirs = [run / f"seed_{s}" for s in seeds]
    timed([*argv, "eval.plots=false", "progress=false"], run.with_suffix(".log"))
    return [json.loads((d / "eval.json").read_text()) for d in dirs]


def quality(args: argparse.Namespace) -> list[str]:
    lines = ["| task / preset | seeds | pass | max abs V error (median, max) | frames per seed |"]
    lines.append("|---|---|---|---|---|")
    notes = []
    schedule = [] if args.schedule == "backward" else [f"schedule={args.schedule}"]
    for variant in args.variants:
        for way in ways(args):
            name = f"quality_{variant}" + (
                "" if args.schedule == "backward" else f"_{args.schedule}"
            )
            overrides = [*VARIANTS[variant], *schedule]
            results = train_seeds(way, overrides, args.seeds, args.out / name)
            rows = [grid_row(variant, s, r) for s, r in zip(args.seeds, results, strict=True)]
            errors = [r["value_error"] for r in rows]
            frames = [r["frames"] for r in rows]
            failed = [r["seed"] for r in rows if not r["pass"]]
            label = (
                variant if not (schedule or args.apart) else f"{variant}, {args.schedule}, {way}"
            )
            lines.append(
                f"| grid world / {label} | {args.seeds[0]}-{args.seeds[-1]} | "
                f"{len(rows) - len(failed)}/{len(rows)} | {statistics.median(errors):.3f}, "
                f"{max(errors):.3f} | median {statistics.median(frames):.0f} |"
            )
            if failed:
                notes.append(f"- grid world / {label}: seeds that fail a bar: {failed}")
    if args.manipulator:
        experiment, algo = args.manipulator_experiment, args.manipulator_algo
        task = [f"experiment={experiment}" if experiment else "task=manipulator"]
        task += [f"algo@task.stages.{stage}={algo}" for stage in ("coarse", "fine") if algo]
        which = experiment or algo
        name = f"manipulator ({which})" if which else "manipulator"
        run = "_".join(["manipulator", *([algo] if algo else [])]) if not experiment else experiment
        lines += success_rows(args, name, run, task, args.manipulator)
    if args.cargo:
        lines += success_rows(args, "cargo", "cargo", ["task=cargo"], args.cargo)
    return [*lines, "", *notes]


def success_rows(
    args: argparse.Namespace, name: str, run: str, task: list[str], seeds: list[int]
) -> list[str]:
    """``seeds`` of ``task`` (its overrides) in one process (and with ``--apart`` each in a
    run of its own, one after another): the rows of their whole-task success rates against
    the 95% bar."""
    rows = []
    for way in ways(args):
        results = train_seeds(way, task, seeds, args.out / f"quality_{run}")
        rates = [r["success_rate"] for r in results]
        frames = [sum(st["frames"] for st in r["training"]["stages"]) for r in results]
        label = f"{name}, {way}" if args.apart else name
        rows.append(
            f"| {label} | {seeds[0]}-{seeds[-1]} | {sum(x >= 0.95 for x in rates)}/"
            f"{len(rates)} at >= 95% success ({', '.join(f'{x:.1%}' for x in rates)}) | - | "
            f"median {statistics.median(frames):.0f} |"
        )
    return rows


def timing(args: argparse.Namespace) -> list[str]:
    measured: dict[str, list[tuple[float, float]]] = {way: [] for way in args.ways}
    for rep in range(args.repeats):
        order = args.ways if rep % 2 == 0 else tuple(reversed(args.ways))
        for way in order:
            out = args.out / f"timing_{way}_{rep}"
            argv = sweep_argv(way, args.seeds, out, args.jobs, args.overrides)
            seconds, rss = timed(argv, out.with_suffix(".log"))
            measured[way].append((seconds, rss))
            print(f"{way} (repeat {rep}): {seconds:.1f} s, {rss:.0f} MiB", flush=True)
    sequential = [s for s, _ in measured.get("sequential", [])]
    base = statistics.median(sequential) if sequential else None
    lines = [
        f"| {len(args.seeds)} grid-world seeds, launched as | wall-clock (s), each repeat | "
        "median | vs sequential | largest resident memory (MiB) |",
        "|---|---|---|---|---|",
    ]
    for way in args.ways:
        secs = [s for s, _ in measured[way]]
        med = statistics.median(secs)
        lines.append(
            f"| {way} | {', '.join(f'{s:.1f}' for s in secs)} | {med:.1f} | "
            f"{f'{base / med:.2f}x' if base else '-'} | "
            f"{max(r for _, r in measured[way]):.0f} |"
        )
    notes = []
    if args.memory:
        one = args.out / "memory_one_seed"
        argv = sweep_argv("vectorized", args.seeds[:1], one, overrides=args.overrides)
        _, rss_one = timed(argv, one.with_suffix(".log"))
        rss_all = max(r for _, r in measured["vectorized"])
        per_seed = (rss_all - rss_one) / max(len(args.seeds) - 1, 1)
        notes.append(
            f"- memory: one seed in one process {rss_one:.0f} MiB, {len(args.seeds)} seeds "
            f"{rss_all:.0f} MiB: {per_seed:.1f} MiB per added seed"
        )
    return [*lines, "", *notes]


def scaling(args: argparse.Namespace) -> list[str]:
    """The grid world's first ``n`` seeds vectorized on ``args.device``, for each ``n`` of
    ``args.scaling``, and one seed on the CPU as the sequential reference."""
    lines = [
        "| seeds in one process | device | wall-clock (s) | per seed (s) | pass | "
        "frames per seed (median, max) | largest resident memory (MiB) | GPU memory (MiB) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    # the reference is an ordinary single run (seed=0) on the CPU, as a sequential sweep runs each
    for sequential, n, device in [(True, 1, "cpu")] + [
        (False, n, args.device) for n in args.scaling
    ]:
        seeds = list(range(n))
        run_dir = args.out / (f"sequential_{device}" if sequential else f"scaling_{n}_{device}")
        runs = "seed=0" if sequential else f"seeds=[{','.join(map(str, seeds))}]"
        argv = [stages_train(), runs, f"device={device}", f"hydra.run.dir={run_dir}"]
        argv += ["eval.plots=false", "progress=false", *(["threads=1"] if sequential else [])]
        with GPUMemory() as gpu:
            seconds, rss = timed(argv, run_dir.with_suffix(".log"))
        if sequential:
            results = [json.loads((run_dir / "eval.json").read_text())]
        else:
            results = seed_results(run_dir, seeds)
        rows = [grid_row("homo", s, r) for s, r in zip(seeds, results, strict=True)]
        frames = [r["frames"] for r in rows]
        failed = [r["seed"] for r in rows if not r["pass"]]
        shown = "-" if sequential or gpu.peak is None else f"{gpu.peak:.0f}"
        way = "1 (one run, threads=1)" if sequential else str(n)
        lines.append(
            f"| {way} | {device} | {seconds:.1f} | {seconds / n:.2f} | {n - len(failed)}/{n} | "
            f"{statistics.median(frames):.0f}, {max(frames)} | {rss:.0f} | {shown} |"
        )
        print(lines[-1], flush=True)
        if failed:
            lines.append(f"<!-- {n} seeds on {device}: seeds that fail a bar: {failed} -->")
    return lines


def device_note() -> str:
    """The machine the table ran on: its CPUs and, where there is one, the GPU and torch."""
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return f"- torch {torch.__version__}, {os.cpu_count()} CPUs, {gpu}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--quality", action="store_true")
    parser.add_argument("--variants", nargs="*", default=["homo", "hetero"], choices=list(VARIANTS))
    parser.add_argument(
        "--schedule",
        default="backward",
        choices=["backward", "joint", "flat"],
        help="--quality's schedule",
    )
    parser.add_argument(
        "--apart", action="store_true", help="--quality: also each seed in a run of its own"
    )
    parser.add_argument("--manipulator", type=int, nargs="*", default=[], help="its seeds")
    parser.add_argument("--cargo", type=int, nargs="*", default=[], help="its seeds")
    parser.add_argument(
        "--manipulator-experiment",
        default="",
        help="train the manipulator's seeds with experiment=<this> (e.g. manipulator_td3)",
    )
    parser.add_argument(
        "--manipulator-algo",
        default="",
        help="train both of the manipulator's stages with this algorithm (e.g. sac)",
    )
    parser.add_argument("--timing", action="store_true")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--ways", nargs="+", default=list(WAYS), choices=WAYS, help="--timing's")
    parser.add_argument("--jobs", type=int, default=2, help="the joblib way's jobs at a time")
    parser.add_argument("--memory", action="store_true")
    parser.add_argument("--scaling", type=int, nargs="*", default=[], help="numbers of seeds")
    parser.add_argument("--device", default="cpu", help="--scaling's device (cuda: a GPU)")
    parser.add_argument("--out", type=Path, required=True)
    add_table_argument(parser)
    parser.add_argument("overrides", nargs="*", help="--timing's: Hydra overrides of every run")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    speed = machine_speed()
    table = [f"```text\n$ {command_line()}\n```", ""]
    if args.quality:
        table += quality(args)
    if args.timing:
        table += ["", *timing(args)] if args.quality else timing(args)
    if args.scaling:
        table += ["", *scaling(args)] if args.quality or args.timing else scaling(args)
    table.append(speed_note(speed, machine_speed()))
    table.append(device_note())
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
