"""Manipulator benchmark: SDQL (DDPG, TD3) against single-stage DDPG at equal frame budgets.

Variants, each trained with the same seeds:
  (a) SDQL, two DDPG stages (coarse u_max 0.25, fine u_max 0.05 with a rescaled observation)
  (b) SDQL, two TD3 stages (experiment=manipulator_td3: its own preset and 300 000-frame budgets)
  (c) one DDPG learner, u_max 0.25, on the same sparse task
  (d) one DDPG learner, u_max 0.05
(a), (c) and (d) get the same total budget: ``--frames`` per SDQL stage (default: the task
config's), twice that for a single learner.
For each it prints the success rate over 1000 whole-task episodes from uniform random joint
angles (d <= 0.01 within 50 steps), mean steps of successful episodes, final-distance
percentiles, training wall-clock and frames.

    python scripts/benchmark_manipulator.py --seeds 0 1 2 [--variants a c] [--frames N] [OVERRIDE]
"""

from __future__ import annotations

import statistics
from pathlib import Path

from _benchmark import checkpoint_share, compose_config, parse_args, run_table, train

SINGLE = ["~task.stages.fine", "task.env.scales=[0.5]"]
VARIANTS = {
    "a": ("SDQL DDPG+DDPG", []),
    "b": ("SDQL TD3+TD3", ["experiment=manipulator_td3"]),
    "c": ("single DDPG u_max 0.25", [*SINGLE, "task.env.u_max=[0.25]"]),
    "d": ("single DDPG u_max 0.05", [*SINGLE, "task.env.u_max=[0.05]"]),
}


def run(variant: str, seed: int, frames: int, out: Path, extra: list[str]) -> dict:
    name, overrides = VARIANTS[variant]
    single = "~task.stages.fine" in overrides
    budget = [f"task.stages.coarse.frames={2 * frames if single else frames}"]
    if not single:
        budget.append(f"task.stages.fine.frames={frames}")
    if variant == "b":  # its preset's own budgets
        budget = []
    result = train(
        "manipulator", out / f"{variant}_seed{seed}", f"seed={seed}", *overrides, *budget, *extra
    )
    return {
        "variant": variant,
        "name": name,
        "seed": seed,
        "success": result["success_rate"],
        "episodes": result["episodes"],
        "steps": result["mean_steps_success"],
        "dist": result["task_metrics"]["final_distance_p50_p90_p99"],
        "seconds": result["training"]["seconds"],
        "checkpoints": checkpoint_share(result),
        "frames": sum(s["frames"] for s in result["training"]["stages"]),
    }


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        succ = [r["success"] for r in rows if r["variant"] == variant]
        seeds = [r["seed"] for r in rows if r["variant"] == variant]
        lines.append(
            f"- ({variant}) {VARIANTS[variant][0]}: mean success {statistics.mean(succ):.1%}, "
            f"lowest {min(succ):.1%}, over seeds {seeds}"
        )
    return lines


def main() -> None:
    args = parse_args(__doc__, list(VARIANTS), frames=None)
    if args.frames is None:  # frame budget per SDQL stage (single learners get twice this)
        args.frames = int(compose_config("manipulator", *args.overrides).task.stages.fine.frames)
    columns = ["variant", "seed", "success", "mean steps (successes)"]
    columns += [
        "final distance p50 / p90 / p99",
        "train wall-clock (s)",
        "checkpoints (s)",
        "env frames",
    ]
    run_table(
        args,
        columns,
        lambda variant, seed: run(variant, seed, args.frames, args.out, args.overrides),
        lambda r: [
            f"({r['variant']}) {r['name']}",
            str(r["seed"]),
            f"{r['success']:.1%}",
            "-" if r["steps"] is None else f"{r['steps']:.1f}",
            " / ".join(f"{d:.3f}" for d in r["dist"]),
            f"{r['seconds']:.0f}",
            r["checkpoints"],
            str(r["frames"]),
        ],
        summary,
    )


if __name__ == "__main__":
    main()
