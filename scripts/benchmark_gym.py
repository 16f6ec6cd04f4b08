"""Bring your own env: the 3-stage waypoints env (``scripts/waypoints.py``) with ``task=gym``'s
defaults, discrete moves (DQN stages) and Box actions (SAC stages), seeds apart.

Each run is the bring-your-own-env guide's command, nothing else set: the stages come from the env
and each is the template's ``stage_template`` (with ``algo@task.stage_template=sac`` for Box
actions). The table gives the whole-task success over 100 episodes from the task's own start, the
frames each stage took (every stage stops early on its criterion, or runs its 200 000-frame budget)
and the training wall-clock.

    python scripts/benchmark_gym.py --seeds 0 1 2 3 4 --out results/gym
"""

from __future__ import annotations

import statistics

from _benchmark import parse_args, run_table, train

VARIANTS = {
    "discrete/dqn": [],
    "box/sac": ["task.env.continuous=true", "algo@task.stage_template=sac"],
}
ENV = [
    "task.env.env_id=waypoints:Waypoints-v0",
    "task.env.stage_fn._target_=waypoints.waypoint_stage",
]


def run(variant: str, seed: int, args) -> dict:
    run_dir = args.out / f"{variant.replace('/', '_')}_seed{seed}"
    result = train("gym", run_dir, *ENV, *VARIANTS[variant], f"seed={seed}", *args.overrides)
    stages = result["training"]["stages"]
    return {
        "variant": variant,
        "seed": seed,
        "success": result["success_rate"],
        "stage_frames": [s["frames"] for s in stages],
        "seconds": result["training"]["seconds"],
    }


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        done = [r for r in rows if r["variant"] == variant]
        lines.append(
            f"- {variant}: success mean {statistics.mean(r['success'] for r in done):.1%} "
            f"(lowest {min(r['success'] for r in done):.1%}); training median "
            f"{statistics.median(r['seconds'] for r in done):.0f} s"
        )
    return lines


def main() -> None:
    args = parse_args(__doc__, list(VARIANTS))
    run_table(
        args,
        ["env / algorithm", "seed", "success", "frames per stage (s0, s1, s2)", "train (s)"],
        lambda variant, seed: run(variant, seed, args),
        lambda r: [
            r["variant"],
            str(r["seed"]),
            f"{r['success']:.1%}",
            ", ".join(str(f) for f in r["stage_frames"]),
            f"{r['seconds']:.0f}",
        ],
        summary,
    )


if __name__ == "__main__":
    main()
