"""Grid-world benchmark: trains discount presets and grid sizes, checks every quality bar.

Variants (the default config plus these overrides):
  homo      gamma 0.99 in every stage (the paper's Fig. 2(b))
  hetero    gamma 0.99 in stage 3 only, 0.9 elsewhere (Fig. 2(c))
  patient1  gamma 0.99 in stage 1 only: every vertical move belongs there
  size20    a 20 x 20 grid with 4 stages, homogeneous
  size30    a 30 x 30 grid with 5 stages (6 columns each), heterogeneous
For each run it reports the training wall-clock, env frames and gradient steps, the success rate
from every column-0 start, the greedy path from (0, 0) against the shortest one and whether its
discounted return is the optimal value of (0, 0) (so, with heterogeneous discounts, whether the
vertical moves are all in the patient stage), the vertical moves per stage, and the merged value
map's largest error against dynamic programming. A run passes when it succeeds from every start,
its path is optimal and the value error is at most 0.05.

    python scripts/benchmark_gridworld.py --seeds 0 1 2 [--variants homo hetero] [--throughput]
"""

from __future__ import annotations

import statistics
from pathlib import Path

from _benchmark import checkpoint_share, parse_args, run_table, train

from torchrl_stages.envs import measure_throughput

PATIENT_1 = [f"task.stages.s{k}.gamma={0.99 if k == 1 else 0.9}" for k in range(5)]
VARIANTS = {
    "homo": ["task/gammas=homo"],
    "hetero": ["task/gammas=hetero"],
    "patient1": PATIENT_1,
    "size20": ["task/gammas=homo", "task.env.size=20", "task.env.num_stages=4", "~task.stages.s4"],
    "size30": ["task/gammas=hetero", "task.env.size=30"],
}
MAX_VALUE_ERROR = 0.05


def run(variant: str, seed: int, out: Path, extra: list[str]) -> dict:
    run_dir = out / f"{variant}_seed{seed}"
    result = train("gridworld", run_dir, f"seed={seed}", *VARIANTS[variant], *extra)
    return grid_row(variant, seed, result)


def grid_row(variant: str, seed: int, result: dict) -> dict:
    """A run's row (its ``eval.json``: ``result``) with the quality bars and ``pass``."""
    stages = result["training"]["stages"]
    m = result["task_metrics"]
    row = {
        "variant": variant,
        "seed": seed,
        "seconds": result["training"]["seconds"],
        "checkpoints": checkpoint_share(result),
        "frames": sum(s["frames"] for s in stages),
        "updates": sum(s["updates"] for s in stages),
        "success": result["success_rate"],
        "path": m["path_from_origin_steps"],
        "shortest": m["optimal_steps_from_origin"],
        "optimal": m["path_from_origin_optimal"],
        "vertical": m["vertical_moves_per_stage"],
        "value_error": m["value_map_max_abs_error"],
    }
    row["pass"] = row["success"] == 1.0 and row["optimal"] and row["value_error"] <= MAX_VALUE_ERROR
    return row


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        done = [r for r in rows if r["variant"] == variant]
        secs = [r["seconds"] for r in done]
        lines.append(
            f"- {variant}: {sum(r['pass'] for r in done)}/{len(done)} runs pass every bar; "
            f"max value error {max(r['value_error'] for r in done):.3f}; train wall-clock "
            f"median {statistics.median(secs):.1f} s, max {max(secs):.1f} s"
        )
    return lines


def main() -> None:
    args = parse_args(__doc__, list(VARIANTS), throughput=False)
    columns = ["variant", "seed", "train wall-clock (s)", "env frames", "gradient steps"]
    columns += ["success (column 0)", "path from (0,0) / shortest", "optimal path"]
    columns += ["vertical moves per stage", "max abs V error", "checkpoints (s)", "pass"]
    run_table(
        args,
        columns,
        lambda variant, seed: run(variant, seed, args.out, args.overrides),
        lambda r: [
            r["variant"],
            str(r["seed"]),
            f"{r['seconds']:.1f}",
            str(r["frames"]),
            str(r["updates"]),
            f"{r['success']:.0%}",
            f"{r['path']} / {r['shortest']}",
            "yes" if r["optimal"] else "no",
            str(r["vertical"]),
            f"{r['value_error']:.3f}",
            r["checkpoints"],
            "yes" if r["pass"] else "**no**",
        ],
        summary,
    )
    if args.throughput:
        print("\n| env batch | frames/s (median of 5) |\n|---|---|")
        for batch in (1, 64, 4096):
            runs = [measure_throughput(batch) for _ in range(5)]
            print(f"| {batch} | {statistics.median(runs):.3g} |")


if __name__ == "__main__":
    main()
