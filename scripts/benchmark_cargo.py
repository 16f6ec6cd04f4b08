"""Cargo-transport benchmark: SDQL (TD3 slider -> DQN self-propelled) against single robots.

Variants, each trained with the same seeds and the same total env-frame budget:
  (a) SDQL: a TD3 slider robot in the left half, a DQN self-propelled robot in the right half
  (b) the self-propelled robot alone for the whole trip (one DQN learner)
  (c) the slider robot alone for the whole trip (one TD3 learner)
For each it prints the success rate over 1000 whole-task greedy episodes from random left-half
starts (within 2 a of the target in 500 steps), mean and median steps to the target (successful
episodes), training wall-clock and env frames. SDQL stages may stop early; single learners get
twice the per-stage budget.

    python scripts/benchmark_cargo.py --seeds 0 1 2 [--variants a b] [--frames N] [OVERRIDE ...]
"""

from __future__ import annotations

import statistics
from pathlib import Path

from _benchmark import checkpoint_share, compose_config, parse_args, run_table, train

VARIANTS = {
    "a": ("SDQL TD3 slider -> DQN propelled", []),
    "b": ("single DQN propelled", ["task.env.robots=[propelled]", "~task.stages.slider"]),
    "c": ("single TD3 slider", ["task.env.robots=[slider]", "~task.stages.propelled"]),
}


def run(variant: str, seed: int, frames: int, out: Path, extra: list[str]) -> dict:
    name, overrides = VARIANTS[variant]
    stages = [s for s in ("slider", "propelled") if f"~task.stages.{s}" not in overrides]
    per_stage = frames if len(stages) == 2 else 2 * frames
    budget = [f"task.stages.{s}.frames={per_stage}" for s in stages]
    result = train(
        "cargo", out / f"{variant}_seed{seed}", f"seed={seed}", *overrides, *budget, *extra
    )
    return {
        "variant": variant,
        "name": name,
        "seed": seed,
        "success": result["success_rate"],
        "episodes": result["episodes"],
        "mean_steps": result["mean_steps_success"],
        "median_steps": result["median_steps_success"],
        "per_robot": result["mean_steps_per_stage"],
        "seconds": result["training"]["seconds"],
        "checkpoints": checkpoint_share(result),
        "frames": sum(s["frames"] for s in result["training"]["stages"]),
    }


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        done = [r for r in rows if r["variant"] == variant]
        steps = [r["mean_steps"] for r in done if r["mean_steps"] is not None]
        lines.append(
            f"- ({variant}) {VARIANTS[variant][0]}: mean success "
            f"{statistics.mean(r['success'] for r in done):.1%}, lowest "
            f"{min(r['success'] for r in done):.1%}, mean steps "
            f"{_fmt(statistics.mean(steps) if steps else None)} over seeds "
            f"{[r['seed'] for r in done]}"
        )
    return lines


def main() -> None:
    args = parse_args(__doc__, list(VARIANTS), frames=None)
    if args.frames is None:  # frame budget per SDQL stage (single learners get twice this)
        args.frames = int(compose_config("cargo", *args.overrides).task.stages.slider.frames)
    columns = ["variant", "seed", "success", "mean / median steps (successes)"]
    columns += ["mean steps per robot", "train wall-clock (s)", "checkpoints (s)", "env frames"]
    run_table(
        args,
        columns,
        lambda variant, seed: run(variant, seed, args.frames, args.out, args.overrides),
        lambda r: [
            f"({r['variant']}) {r['name']}",
            str(r["seed"]),
            f"{r['success']:.1%}",
            f"{_fmt(r['mean_steps'])} / {_fmt(r['median_steps'])}",
            " / ".join(f"{s:.1f}" for s in r["per_robot"]),
            f"{r['seconds']:.0f}",
            r["checkpoints"],
            str(r["frames"]),
        ],
        summary,
    )


if __name__ == "__main__":
    main()
