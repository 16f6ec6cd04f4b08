"""How often a random walk leaves a MiniGrid stage, with and without actions the level never
needs: the exploration a stage's learner starts from.

Each walk starts inside the stage (``StagedMiniGrid(start_stage=k)``, a new layout per walk) and
takes uniformly drawn actions until it leaves the stage (the last one: the level's success) or
``--steps`` run out (or the level's own step limit). Table: walks that
left the stage, per level, stage and action set.

    python scripts/minigrid_random_walks.py --out results/random_walks \
        [--levels MiniGrid-DoorKey-16x16-v0 ...] [--stages 0 1] [--walks 200] [--steps 256]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import gymnasium
import numpy as np
from _benchmark import add_table_argument, command_line, save_table

from torchrl_stages.envs.minigrid import StagedMiniGrid, import_minigrid, level_actions


def walks_leaving(level: str, stage: int, actions: str | None, walks: int, steps: int) -> int:
    """How many of ``walks`` random walks started inside ``stage`` leave it within ``steps``."""
    env = StagedMiniGrid(gymnasium.make(level), start_stage=stage, actions=actions)
    rng = np.random.default_rng(0)
    left = 0
    for walk in range(walks):
        env.reset(seed=walk)
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
            if env.stage > stage or terminated:  # the last stage ends on the level's success
                left += 1
                break
            if truncated:
                break
    env.close()
    return left


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--levels", nargs="+", default=["MiniGrid-DoorKey-8x8-v0", "MiniGrid-DoorKey-16x16-v0"]
    )
    parser.add_argument("--stages", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--walks", type=int, default=200)
    parser.add_argument("--steps", type=int, default=256)
    parser.add_argument("--out", type=Path, default=Path("results/random_walks"))
    add_table_argument(parser)
    args = parser.parse_args()
    import_minigrid()
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [
        "| level | stage | all seven actions | the family's actions |",
        "|---|---|---|---|",
    ]
    rows = []
    for level in args.levels:
        for stage in args.stages:
            every = walks_leaving(level, stage, "all", args.walks, args.steps)
            family = walks_leaving(level, stage, None, args.walks, args.steps)
            rows.append({"level": level, "stage": stage, "all": every, "family": family})
            names = ", ".join(level_actions(level))
            lines.append(f"| {level} | {stage} | {every} | {family} ({names}) |")
            print(lines[-1], flush=True)
    (args.out / "rows.json").write_text(json.dumps(rows, indent=2))
    note = f"- walks that leave the stage, of {args.walks} walks of {args.steps} random steps"
    table = ["```text", f"$ {command_line()}", "```", "", *lines, "", note]
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
