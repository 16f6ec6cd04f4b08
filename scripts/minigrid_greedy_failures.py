"""Where a MiniGrid run's greedy stage policy fails: the loop each failed episode ends in.

For each run directory, the kept learner of ``--stage`` acts greedily from ``--starts`` drawn
starts of its stage (``StagedMiniGrid(start_stage=k)``, the run's own env keys, seeds 1000 on:
layouts the run's evaluations did not draw) until it leaves the stage or ``--steps`` run out.
A failed episode is classified by its last ``--tail`` actions: one action repeated (``repeats
toggle``: with nothing toggled, it changes nothing), two alternating (``alternates left,
right``), or anything else. Table: per run, the starts left and the failures by kind.

    python scripts/minigrid_greedy_failures.py --stage 0 --out results/failures RUN_DIR [...]
"""

from __future__ import annotations

import argparse
import collections
import inspect
from pathlib import Path

import gymnasium
import torch
from _benchmark import add_table_argument, command_line, save_table
from tensordict import TensorDict

from torchrl_stages import load_run
from torchrl_stages.envs.minigrid import StagedMiniGrid, import_minigrid

#: the run's env keys the wrapper takes (the rest are the level's own); those but ``actions``
#: are the settings the table shows
WRAPPER_KEYS = tuple(inspect.signature(StagedMiniGrid).parameters)[2:]  # after env, start_stage


def loop_kind(actions: list[str]) -> str:
    """``repeats a``, ``alternates a, b`` or ``other`` for the tail of a failed episode.

    Examples:
        >>> loop_kind(["left", "toggle", "toggle", "toggle"][1:])
        'repeats toggle'
        >>> loop_kind(["left", "right", "left", "right"]), loop_kind(["left", "forward", "pickup"])
        ('alternates left, right', 'other')
    """
    if len(set(actions)) == 1:
        return f"repeats {actions[0]}"
    if len(set(actions)) == 2 and all(a != b for a, b in zip(actions, actions[1:], strict=False)):
        return f"alternates {', '.join(sorted(set(actions)))}"
    return "other"


def failures(
    run_dir: Path, stage: int, starts: int, steps: int, tail: int
) -> tuple[str, int, dict]:
    """The run's settings that bear on loops, the starts of ``stage`` its greedy learner
    leaves, and its failures by loop kind."""
    run = load_run(run_dir)
    learner = run.learners[stage]
    policy = learner.policy
    keys = run.cfg.task.env
    wrapper = {k: keys[k] for k in WRAPPER_KEYS if k in keys}
    env = StagedMiniGrid(
        gymnasium.make(str(keys.env_id), max_steps=steps), start_stage=stage, **wrapper
    )
    # the wrapper's settings as it applies them (view_doors=null: from the level's doors)
    settings = [f"{k}={getattr(env, k)}" for k in WRAPPER_KEYS[1:] if getattr(env, k)]
    settings.append(f"gamma={learner.cfg.gamma}")
    if getattr(learner.cfg, "advantage_learning", 0):
        settings.append(f"advantage_learning={learner.cfg.advantage_learning}")
    left, kinds = 0, collections.Counter()
    for seed in range(1000, 1000 + starts):
        obs, _ = env.reset(seed=seed)
        taken = []
        for _ in range(steps):
            td = TensorDict(
                {k: torch.as_tensor(v).unsqueeze(0) for k, v in obs.items()}, batch_size=[1]
            )
            with torch.no_grad():
                action = int(policy(td).get("action").reshape(-1)[0])
            taken.append(env.actions[action])
            obs, _, terminated, truncated, _ = env.step(action)
            if env.stage > stage or terminated or truncated:
                break
        if env.stage > stage or terminated:
            left += 1
        else:
            kinds[loop_kind(taken[-tail:])] += 1
    env.close()
    return ", ".join(settings), left, dict(kinds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run directories of task=minigrid")
    parser.add_argument("--stage", type=int, required=True)
    parser.add_argument("--starts", type=int, default=100)
    parser.add_argument("--steps", type=int, default=256)
    parser.add_argument("--tail", type=int, default=8, help="actions that classify a failure")
    parser.add_argument("--out", type=Path, required=True)
    add_table_argument(parser)
    args = parser.parse_args()
    import_minigrid()
    args.out.mkdir(parents=True, exist_ok=True)
    table = [
        f"```text\n$ {command_line()}\n```",
        "",
        "| run | settings | stage | left the stage | failures: the loop they end in |",
        "|---|---|---|---|---|",
    ]
    names = [run_dir.name for run_dir in args.runs]
    for run_dir in args.runs:
        settings, left, kinds = failures(run_dir, args.stage, args.starts, args.steps, args.tail)
        ranked = sorted(kinds.items(), key=lambda kv: (-kv[1], kv[0]))
        loops = "; ".join(f"{kind} {n}" for kind, n in ranked) or "-"
        # runs of the same level, schedule and seed from two launches: their launch names them
        unique = names.count(run_dir.name) == 1
        name = run_dir.name if unique else f"{run_dir.parent.name}/{run_dir.name}"
        table.append(f"| {name} | {settings} | {args.stage} | {left}/{args.starts} | {loops} |")
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
