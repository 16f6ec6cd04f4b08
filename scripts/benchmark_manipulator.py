"""Manipulator benchmark: SDQL (DDPG, TD3) against single-stage DDPG at equal frame budgets.

Variants, each trained with the same seeds and the same total env-frame budget:
  (a) SDQL, two DDPG stages (coarse u_max 0.25, fine u_max 0.05 with a rescaled observation)
  (b) SDQL, two TD3 stages
  (c) one DDPG learner, u_max 0.25, on the same sparse task
  (d) one DDPG learner, u_max 0.05
For each it prints the success rate over 1000 whole-task episodes from uniform random joint
angles (d <= 0.01 within 50 steps), mean steps of successful episodes, final-distance
percentiles, training wall-clock and frames.

    python scripts/benchmark_manipulator.py --seeds 0 1 2 [--variants a c] [--frames 200000]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_module

from torchrl_stages.cli import run_training
from torchrl_stages.config import register_configs

SINGLE = ["~task.stages.fine", "task.env.scales=[0.5]"]
VARIANTS = {
    "a": ("SDQL DDPG+DDPG", []),
    "b": ("SDQL TD3+TD3", ["algo@task.stages.coarse=td3", "algo@task.stages.fine=td3"]),
    "c": ("single DDPG u_max 0.25", [*SINGLE, "task.env.u_max=[0.25]"]),
    "d": ("single DDPG u_max 0.05", [*SINGLE, "task.env.u_max=[0.05]"]),
}


def run(variant: str, seed: int, frames: int, out: Path) -> dict:
    name, overrides = VARIANTS[variant]
    single = "~task.stages.fine" in overrides
    budget = [f"task.stages.coarse.frames={2 * frames if single else frames}"]
    if not single:
        budget.append(f"task.stages.fine.frames={frames}")
    with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        cfg = compose(
            "config",
            overrides=["task=manipulator", f"seed={seed}", "logger=csv", *overrides, *budget],
        )
    run_dir = out / f"{variant}_seed{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    result = run_training(cfg, run_dir)
    m = result["task_metrics"]
    return {
        "variant": variant,
        "name": name,
        "seed": seed,
        "success": m["success_rate"],
        "steps": m["mean_steps_success"],
        "dist": m["final_distance_p50_p90_p99"],
        "seconds": result["training"]["seconds"],
        "frames": sum(s["frames"] for s in result["training"]["stages"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frame budget per SDQL stage (single learners get twice this); "
        "default: the task config's",
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    register_configs()
    out = args.out or Path(tempfile.mkdtemp(prefix="manipulator_bench_"))
    if args.frames is None:
        with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
            args.frames = int(
                compose("config", overrides=["task=manipulator"]).task.stages.fine.frames
            )
    print(
        f"runs in {out}; budget {args.frames} frames per SDQL stage, "
        f"{2 * args.frames} for single learners"
    )
    print(
        "| variant | seed | success (1000 eps) | mean steps (successes) "
        "| final distance p50 / p90 / p99 | train wall-clock (s) | env frames |"
    )
    print("|---|---|---|---|---|---|---|")
    rows = []
    for variant in args.variants:
        for seed in args.seeds:
            r = run(variant, seed, args.frames, out)
            rows.append(r)
            dist = " / ".join(f"{d:.3f}" for d in r["dist"])
            print(
                f"| ({r['variant']}) {r['name']} | {r['seed']} | {r['success']:.1%} | "
                f"{r['steps']:.1f} | {dist} | {r['seconds']:.0f} | {r['frames']} |",
                flush=True,
            )
    for variant in args.variants:
        succ = [r["success"] for r in rows if r["variant"] == variant]
        print(
            f"({variant}) {VARIANTS[variant][0]}: mean success {statistics.mean(succ):.1%} "
            f"over seeds {args.seeds}"
        )


if __name__ == "__main__":
    main()
