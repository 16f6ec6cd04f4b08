"""What the SDQL-against-baselines benchmark scripts share: arguments, configs, training a run."""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from torchrl_stages.cli import run_training
from torchrl_stages.config import register_configs


def compose_config(task: str, *overrides: str) -> DictConfig:
    with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        return compose("config", overrides=[f"task={task}", *overrides])


def parse_args(doc: str, variants: list[str], task: str, stage: str) -> argparse.Namespace:
    """``--seeds``, ``--variants``, ``--frames`` (default: ``task.stages.<stage>.frames``) and
    ``--out`` (default: a temporary directory); also sets one torch thread."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=variants, choices=variants)
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frame budget per SDQL stage (single learners get twice this); "
        "default: the task config's",
    )
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "overrides", nargs="*", help="extra Hydra overrides for every run, e.g. task.env.window=12"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    register_configs()
    args.out = args.out or Path(tempfile.mkdtemp(prefix=f"{task}_bench_"))
    if args.frames is None:
        args.frames = int(compose_config(task, *args.overrides).task.stages[stage].frames)
    print(
        f"runs in {args.out}; budget {args.frames} frames per SDQL stage, "
        f"{2 * args.frames} for single learners"
    )
    return args


def train(task: str, run_dir: Path, *overrides: str) -> dict[str, Any]:
    """Trains and evaluates one run in ``run_dir`` (CSV logger); returns its ``eval.json``."""
    cfg = compose_config(task, "logger=csv", *overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_training(cfg, run_dir)


def run_table(
    args: argparse.Namespace,
    columns: list[str],
    run_one: Callable[[str, int], dict[str, Any]],
    cells: Callable[[dict[str, Any]], list[str]],
) -> list[dict[str, Any]]:
    """Runs every (variant, seed) of ``args`` and prints a markdown row as each one finishes."""
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    rows = []
    for variant in args.variants:
        for seed in args.seeds:
            row = run_one(variant, seed)
            rows.append(row)
            print("| " + " | ".join(cells(row)) + " |", flush=True)
    return rows
