"""The shaping a Meta-World stage learns from: each stage's potential along episodes of the
task's scripted policy, from the benchmark's own starts.

Each episode starts from a seeded reset and follows the scripted policy (``metaworld.policies``)
to success. Table: per task, the potential ``Phi`` (``StagedMetaWorld.potential``) at the start,
after a quarter, a half and three quarters of the grasp stage's steps, on its last step, and at
the first step of the place stage and on the step before success (means over the episodes).

    python scripts/metaworld_potentials.py --out results/metaworld_potentials \
        [--tasks pick-place-v3 ...] [--episodes 20]
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
from _benchmark import add_table_argument, command_line, save_table

from torchrl_stages.envs.metaworld import StagedMetaWorld, make_task

POINTS = ("start", "1/4", "1/2", "3/4", "grasp's last step", "place's first step", "last step")


def potentials(task: str, episodes: int) -> np.ndarray:
    """``[episodes, len(POINTS)]``: the potential at each point of each scripted episode."""
    env = StagedMetaWorld(make_task(task), task)
    rows = []
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        trace, stages = [env.potential], [0]
        for _ in range(500):
            with warnings.catch_warnings():  # its gains warn that the env clips the actions
                warnings.simplefilter("ignore", UserWarning)
                action = env.scripted.get_action(obs["observation"].astype(np.float64))
            obs, _, terminated, truncated, _ = env.step(action)
            trace.append(env.potential)
            stages.append(env.stage)
            if terminated or truncated:
                break
        if not terminated or 1 not in stages:
            continue  # only episodes that grasp, then succeed
        handoff = stages.index(1)  # the first state of the place stage
        grasp = [round(handoff * f) for f in (0.0, 0.25, 0.5, 0.75)] + [handoff - 1]
        rows.append([trace[i] for i in grasp] + [trace[handoff], trace[-2]])
    env.close()
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["pick-place-v3"])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("results/metaworld_potentials"))
    add_table_argument(parser)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [
        "| task | episodes | " + " | ".join(POINTS) + " |",
        "|---|---|" + "---|" * len(POINTS),
    ]
    for task in args.tasks:
        rows = potentials(task, args.episodes)
        means = " | ".join(f"{v:.3f}" for v in rows.mean(0))
        lines.append(f"| {task} | {len(rows)} | {means} |")
    table = ["```text", f"$ {command_line()}", "```", "", *lines]
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
