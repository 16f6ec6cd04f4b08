"""One stage trained alone: frames, updates and wall-clock to its early stop, per override set.

The backward schedule trains stage K once the value of stage K+1 is fixed, so a stage's
hyper-parameters can be compared on that stage alone, in seconds instead of whole runs. This
trains stage K of a task for every (variant, seed): ``torchrl_stages.schedules.train_stage``
with the run's config plus the variant's Hydra overrides, seeded as the backward schedule seeds
the stage, so that a row is stage K of a whole run with that seed, given the same stage K+1.
For K < N-1, ``--next-run`` names a finished run directory whose stage K+1 supplies the value
(the same for every row); the last stage needs none. Each row reports the evaluation the
stage ends with (its stop, or its best evaluation when the budget ran out): success, value
error and mean discounted return, the objective of a stage without an early stop (cargo's
slider).

A variant is ``NAME:OVERRIDE ...`` (``base:`` for the config as it is), e.g.

    python scripts/benchmark_stage.py --task gridworld --stage 4 --seeds 100 101 102 \\
        --variant base: --variant "tau0.1: task.stages.s4.tau=0.1"
    python scripts/benchmark_stage.py --task gridworld --stage 3 --next-run RUN_DIR --seeds 0
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

import torch
from _benchmark import command_line, compose_config, run_table

from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS
from torchrl_stages.runs.experiment import build_task, compile_mode
from torchrl_stages.runs.loading import load_run
from torchrl_stages.schedules import train_stage

COLUMNS = [
    "variant",
    "seed",
    "frames",
    "updates",
    "train (s)",
    "success",
    "value error",
    "return",
    "early stop",
]


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``"NAME:OVERRIDE ..."`` -> ``(NAME, [OVERRIDE, ...])``."""
    name, sep, rest = text.partition(":")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(
            f"--variant {text!r}: expected NAME:OVERRIDE ..., e.g. 'tau0.1: task.stages.s4.tau=0.1'"
            " ('base:' for no override)"
        )
    return name.strip(), shlex.split(rest)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="gridworld", help="a conf/task name")
    parser.add_argument("--stage", type=int, required=True, help="the stage index K")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--variant", dest="variant_list", type=parse_variant, action="append", default=None
    )
    parser.add_argument("--next-run", type=Path, default=None, help="a run with stage K+1")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every variant")
    args = parser.parse_args()
    args.variant_list = args.variant_list or [("base", [])]
    names = [name for name, _ in args.variant_list]
    if len(set(names)) != len(names):
        parser.error(f"--variant names must differ, got {names}")
    args.variants = names
    args.out = args.out or Path(tempfile.mkdtemp(prefix="benchmark_stage_"))
    args.out.mkdir(parents=True, exist_ok=True)
    args.command = command_line()
    return args


def next_stage_value(args: argparse.Namespace, num_stages: int):
    """Stage K+1's value from ``--next-run`` (``None`` for the last stage)."""
    last = args.stage == num_stages - 1
    if last and args.next_run is not None:
        sys.exit(f"error: stage {args.stage} is the last of {num_stages}; drop --next-run")
    if last:
        return None
    if args.next_run is None:
        sys.exit(
            f"error: stage {args.stage} of {num_stages} needs the value of stage "
            f"{args.stage + 1}: pass --next-run RUN_DIR (a finished run of this task)"
        )
    run = load_run(args.next_run)
    if run.task.num_stages != num_stages:
        sys.exit(
            f"error: {args.next_run} has {run.task.num_stages} stages, this task {num_stages}: "
            "pass a run of the same task and overrides"
        )
    return run.learners[args.stage + 1].value()


def main() -> None:
    args = parse_args()
    register_configs(ALGORITHMS)
    overrides = dict(args.variant_list)
    base = build_task(compose_config(args.task, *args.overrides))
    if not 0 <= args.stage < base.num_stages:
        sys.exit(f"error: --stage {args.stage} is outside 0..{base.num_stages - 1}")
    next_value = next_stage_value(args, base.num_stages)
    print(f"{args.command}\ntorch {torch.__version__}; runs in {args.out}", flush=True)

    def run_one(variant: str, seed: int) -> dict:
        cfg = compose_config(args.task, f"seed={seed}", *args.overrides, *overrides[variant])
        torch.set_num_threads(int(cfg.threads))
        task = build_task(cfg)
        [(_, result)] = train_stage(
            task, args.stage, next_value, seeds=[seed], compile=compile_mode(cfg)
        )
        return {"variant": variant, "seed": seed, **vars(result)}

    def cells(row: dict) -> list[str]:
        success, error = row["success_rate"], row["value_error"]
        ret = row["discounted_return"]
        return [
            row["variant"],
            str(row["seed"]),
            str(row["frames"]),
            str(row["updates"]),
            f"{row['seconds']:.1f}",
            "-" if success is None else f"{success:.1%}",
            "-" if error is None else f"{error:.4f}",
            "-" if ret is None else f"{ret:.4f}",
            "yes" if row["early_stopped"] else "no",
        ]

    def summary(rows: list[dict]) -> list[str]:
        notes = []
        for name in args.variants:
            mine = [r for r in rows if r["variant"] == name]
            frames = [r["frames"] for r in mine]
            errors = [r["value_error"] for r in mine if r["value_error"] is not None]
            returns = [r["discounted_return"] for r in mine if r["discounted_return"] is not None]
            notes.append(
                f"- {name} ({shlex.join(overrides[name]) or 'no override'}): frames median "
                f"{statistics.median(frames):.0f}, mean {statistics.mean(frames):.0f}; updates "
                f"median {statistics.median(r['updates'] for r in mine):.0f}; train median "
                f"{statistics.median(r['seconds'] for r in mine):.1f} s; early stops "
                f"{sum(r['early_stopped'] for r in mine)}/{len(mine)}"
                + (f"; max value error {max(errors):.4f}" if errors else "")
                + (
                    f"; return median {statistics.median(returns):.4f}, min {min(returns):.4f}"
                    if returns
                    else ""
                )
            )
        return notes

    run_table(args, COLUMNS, run_one, cells, summary)


if __name__ == "__main__":
    main()
