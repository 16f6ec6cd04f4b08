"""What the benchmark scripts share: arguments, configs, training one run, the results table.

Every script writes its rows as ``rows.json`` and its table as ``table.md`` (the command that
made it on top) into its output directory, and with ``--table docs/tables/<name>.md`` to the
file the docs include: a published table is written by the script, never typed.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from torchrl_stages.config import register_configs
from torchrl_stages.envs import measure_throughput
from torchrl_stages.learners import ALGORITHMS
from torchrl_stages.runs.experiment import Experiment


def compose_config(task: str, *overrides: str) -> DictConfig:
    with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        return compose("config", overrides=[f"task={task}", *overrides])


# environment variables that change what a timed run measures, shown in front of its command
TIMING_ENV = ("TORCHINDUCTOR_CACHE_DIR", "OMP_NUM_THREADS", "CUDA_VISIBLE_DEVICES")


def _launch_environ() -> dict[str, str]:
    """The environment the process was started with: importing torchrl sets
    ``TORCHINDUCTOR_CACHE_DIR`` in ``os.environ`` (Linux keeps the original in /proc)."""
    try:
        raw = Path("/proc/self/environ").read_bytes().decode(errors="replace")
    except OSError:
        return dict(os.environ)
    return dict(item.split("=", 1) for item in raw.split("\0") if "=" in item)


def add_table_argument(parser: argparse.ArgumentParser) -> None:
    """``--table PATH``: a second copy of ``table.md`` (e.g. ``docs/tables/<name>.md``)."""
    parser.add_argument(
        "--table", type=Path, default=None, help="also write the table here (docs/tables/...)"
    )


def save_table(out: Path, table: list[str], also: Path | None = None) -> None:
    """Writes ``table`` as ``out/table.md`` and, when given, to ``also`` (the docs' copy)."""
    text = "\n".join(table) + "\n"
    (out / "table.md").write_text(text)
    if also is not None:
        also.parent.mkdir(parents=True, exist_ok=True)
        also.write_text(text)
        print(f"wrote {also}")


def command_line() -> str:
    """This script's command as typed, with the :data:`TIMING_ENV` variables it was launched
    with (an empty inductor cache makes a compiled run pay its compilation) in front."""
    launch = _launch_environ()
    env = [f"{name}={shlex.quote(launch[name])}" for name in TIMING_ENV if name in launch]
    argv = shlex.join([os.path.relpath(sys.argv[0]), *portable(sys.argv[1:])])
    return " ".join([*env, "python", argv])


def portable(argv: list[str]) -> list[str]:
    """``argv`` with the paths under the ``--out`` directory's parent (a scratch folder of the
    machine it ran on) as ``runs/...``, so that the command shown runs anywhere.

    Examples:
        >>> portable(["--out", "/scratch/b/x", "--next-run=/scratch/b/y/s0", "/etc/z"])
        ['--out', 'runs/x', '--next-run=runs/y/s0', '/etc/z']
    """
    out = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--out"), None)
    if out is None or not os.path.isabs(out):
        return argv
    scratch = os.path.dirname(os.path.normpath(out)) + os.sep

    def fix(token: str) -> str:
        key, eq, value = token.rpartition("=") if "=" in token else ("", "", token)
        if not value.startswith(scratch):
            return token
        return f"{key}{eq}runs/{value.removeprefix(scratch)}"

    return [fix(token) for token in argv]


def parse_args(doc: str, variants: list[str], **extra: Any) -> argparse.Namespace:
    """``--seeds``, ``--variants``, ``--out`` (default: a temporary directory) and extra Hydra
    overrides for every run; ``extra`` adds ``--name default`` options."""
    parser = argparse.ArgumentParser(
        description=doc.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=variants, choices=variants)
    for name, default in extra.items():
        if isinstance(default, bool):
            parser.add_argument(f"--{name}", action="store_true")
        else:
            parser.add_argument(f"--{name}", type=type(default), default=default)
    parser.add_argument("--out", type=Path, default=None)
    add_table_argument(parser)
    parser.add_argument(
        "overrides", nargs="*", help="extra Hydra overrides for every run, e.g. task.env.size=20"
    )
    args = parser.parse_args()
    register_configs(ALGORITHMS)
    args.out = args.out or Path(tempfile.mkdtemp(prefix="benchmark_"))
    args.out.mkdir(parents=True, exist_ok=True)
    args.command = command_line()
    print(
        f"{args.command}\ntorch {torch.__version__}, {os.cpu_count()} CPUs (torch threads: "
        f"the config's `threads`); runs in {args.out}",
        flush=True,
    )
    return args


def train(task: str, run_dir: Path, *overrides: str) -> dict[str, Any]:
    """Trains and evaluates one run in ``run_dir`` (CSV logger); returns its ``eval.json``."""
    cfg = compose_config(task, "logger=csv", *overrides)
    [result] = Experiment(cfg, run_dir).run()
    return result


def checkpoint_share(result: dict[str, Any]) -> str:
    """Wall-clock of a run's mid-stage checkpoints, in seconds and as a share of its training."""
    stages = result["training"]["stages"]
    seconds = sum(stage.get("timing", {}).get("checkpoint", 0.0) for stage in stages)
    return f"{seconds:.1f} ({seconds / result['training']['seconds']:.1%})"


def machine_speed() -> float:
    """This machine's speed now: frames per second of the grid world env alone (64 envs, random
    actions, median of 5 short runs), code that training changes leave alone. This project's
    CPU machine drifts by hours, by two times and more; wall-clocks of two tables compare only
    at similar speeds."""
    return statistics.median(measure_throughput(64) for _ in range(5))


def speed_note(before: float, after: float) -> str:
    """The summary line of :func:`machine_speed` before and after a table's runs."""
    return (
        f"- machine speed (grid world env alone, 64 envs): {before:.3g} frames/s before these "
        f"runs, {after:.3g} after"
    )


def run_table(
    args: argparse.Namespace,
    columns: list[str],
    run_one: Callable[[str, int], dict[str, Any]],
    cells: Callable[[dict[str, Any]], list[str]],
    summary: Callable[[list[dict[str, Any]]], list[str]] | None = None,
) -> list[dict[str, Any]]:
    """Runs every (variant, seed) of ``args``, printing a markdown row as each one finishes;
    writes ``rows.json`` and ``table.md`` (command, table, ``summary`` lines and the machine's
    speed before and after, :func:`machine_speed`) into ``args.out``.
    """
    speed = machine_speed()
    header = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    print("\n".join(header), flush=True)
    rows, lines = [], []
    for variant in args.variants:
        for seed in args.seeds:
            row = run_one(variant, seed)
            rows.append(row)
            lines.append("| " + " | ".join(cells(row)) + " |")
            print(lines[-1], flush=True)
            (args.out / "rows.json").write_text(json.dumps(rows, indent=2))
    notes = summary(rows) if summary is not None else []
    notes.append(speed_note(speed, machine_speed()))
    for note in notes:
        print(note)
    table = ["```text", f"$ {args.command}", "```", "", *header, *lines, "", *notes]
    save_table(args.out, table, getattr(args, "table", None))
    print(f"wrote {args.out / 'rows.json'} and {args.out / 'table.md'}")
    return rows
