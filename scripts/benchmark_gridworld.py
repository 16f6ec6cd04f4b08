"""Grid-world benchmark: trains both discount presets to convergence and prints what they learned.

For each preset and seed it prints the training wall-clock, env frames, gradient steps, the
success rate from every column-0 start, the greedy path length from (0, 0) and how many vertical
moves fall in each stage; then the batched env's raw throughput at batch 1, 64 and 4096.

    python scripts/benchmark_gridworld.py --seeds 0 1 2

Runs go to ``--out`` (default: a temporary directory), one run directory each.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_module

from torchrl_stages.cli import run_training
from torchrl_stages.config import register_configs
from torchrl_stages.envs import measure_throughput


def train_preset(preset: str, seed: int, out: Path) -> dict:
    with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        cfg = compose("config", overrides=[f"task/gammas={preset}", f"seed={seed}"])
    run_dir = out / f"{preset}_seed{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    result = run_training(cfg, run_dir)
    stages = result["training"]["stages"]
    metrics = result["task_metrics"]
    return {
        "preset": preset,
        "seed": seed,
        "seconds": result["training"]["seconds"],
        "frames": sum(s["frames"] for s in stages),
        "updates": sum(s["updates"] for s in stages),
        "column0": metrics["column0_success_rate"],
        "path": metrics["path_from_origin_steps"],
        "vertical": metrics["vertical_moves_per_stage"],
        "value_err": metrics["value_map_max_abs_error"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--presets", nargs="+", default=["homo", "hetero"])
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--throughput-steps", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    register_configs()
    out = args.out or Path(tempfile.mkdtemp(prefix="gridworld_bench_"))

    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, 1 torch thread; runs in {out}")
    print(
        "| preset | seed | train wall-clock (s) | env frames | gradient steps | column-0 success "
        "| path from (0,0) | vertical moves per stage | max abs V error |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            r = train_preset(preset, seed, out)
            rows.append(r)
            print(
                f"| {r['preset']} | {r['seed']} | {r['seconds']:.1f} | {r['frames']} | "
                f"{r['updates']} | {r['column0']:.0%} | {r['path']} | {r['vertical']} | "
                f"{r['value_err']:.3f} |",
                flush=True,
            )
    for preset in args.presets:
        secs = [r["seconds"] for r in rows if r["preset"] == preset]
        print(
            f"{preset}: median train wall-clock {statistics.median(secs):.1f} s "
            f"(max {max(secs):.1f} s) over {len(secs)} seeds"
        )

    print("\n| env batch | frames/s (median of 5) |")
    print("|---|---|")
    for batch in (1, 64, 4096):
        runs = [measure_throughput(batch, steps=args.throughput_steps) for _ in range(5)]
        print(f"| {batch} | {statistics.median(runs):.3g} |")


if __name__ == "__main__":
    main()
