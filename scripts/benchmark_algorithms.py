"""Algorithms benchmark: every task's stages with each algorithm that can act in them.

A variant is ``TASK/ALGO``: the task's default config with the stages the algorithm can act in
switched to it (``algo@task.stages.<stage>=ALGO``; the others keep their default). The default
algorithms are the baselines: ``gridworld/dqn``, ``manipulator/ddpg``, ``cargo/default``
(TD3 slider, DQN self-propelled robot). Per run: the whole-task success, the env frames and the
training wall-clock; the grid world's optimal path and value error too.

    python scripts/benchmark_algorithms.py --seeds 0 1 2 3 4 \
        --variants manipulator/ddpg manipulator/sac cargo/default cargo/sac
"""

from __future__ import annotations

import statistics
from pathlib import Path

from _benchmark import parse_args, run_table, train

#: the stages each algorithm is put in (by action space), per task
STAGES = {
    "gridworld": {"discrete": ["s0", "s1", "s2", "s3", "s4"], "continuous": []},
    "manipulator": {"discrete": [], "continuous": ["coarse", "fine"]},
    "cargo": {"discrete": ["propelled"], "continuous": ["slider"]},
}
ALGOS = {
    "dqn": "discrete",
    "discrete_sac": "discrete",
    "ddpg": "continuous",
    "td3": "continuous",
    "sac": "continuous",
}
VARIANTS = [
    "gridworld/dqn",
    "gridworld/discrete_sac",
    "manipulator/ddpg",
    "manipulator/td3",
    "manipulator/sac",
    "cargo/default",
    "cargo/sac",
    "cargo/discrete_sac",
]


def overrides(task: str, algo: str) -> list[str]:
    """``algo@task.stages.<stage>=algo`` for the task's stages of the algorithm's action space."""
    if algo == "default":
        return []
    return [f"algo@task.stages.{stage}={algo}" for stage in STAGES[task][ALGOS[algo]]]


def run(variant: str, seed: int, out: Path, extra: list[str]) -> dict:
    task, algo = variant.split("/")
    run_dir = out / f"{task}_{algo}_seed{seed}"
    result = train(task, run_dir, f"seed={seed}", *overrides(task, algo), *extra)
    metrics = result.get("task_metrics", {})
    return {
        "variant": variant,
        "seed": seed,
        "success": result["success_rate"],
        "frames": sum(stage["frames"] for stage in result["training"]["stages"]),
        "seconds": result["training"]["seconds"],
        "optimal_path": metrics.get("path_from_origin_optimal"),
        "value_error": metrics.get("value_map_max_abs_error"),
    }


def cells(row: dict) -> list[str]:
    optimal = "-" if row["optimal_path"] is None else str(row["optimal_path"])
    error = "-" if row["value_error"] is None else f"{row['value_error']:.3f}"
    return [
        row["variant"],
        str(row["seed"]),
        f"{row['success']:.1%}",
        f"{row['frames']:,}".replace(",", " "),
        f"{row['seconds']:.0f}",
        optimal,
        error,
    ]


def summary(rows: list[dict]) -> list[str]:
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        done = [r for r in rows if r["variant"] == variant]
        success = [r["success"] for r in done]
        frames = statistics.median(r["frames"] for r in done)
        seconds = statistics.median(r["seconds"] for r in done)
        lines.append(
            f"- {variant}: success mean {statistics.mean(success):.1%} (lowest "
            f"{min(success):.1%}), median frames {frames:,.0f}, median training {seconds:.0f} s "
            f"over seeds {[r['seed'] for r in done]}"
        )
    return lines


def main() -> None:
    args = parse_args(__doc__, VARIANTS)
    columns = ["variant", "seed", "success", "frames", "train (s)", "optimal path", "V error"]
    run_table(args, columns, lambda v, s: run(v, s, args.out, args.overrides), cells, summary)


if __name__ == "__main__":
    main()
