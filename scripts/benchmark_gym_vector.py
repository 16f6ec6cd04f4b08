"""Gymnasium envs stepped as one vector env against copies stepped one after another.

Frames per second of random-action steps (``step_and_maybe_reset``, partial resets included)
of ``n`` copies of a gymnasium env, three ways:

* ``serial``: torchrl's ``SerialEnv`` of ``n`` ``GymEnv`` copies (how ``task=gym`` stepped
  before it used gymnasium's vector envs);
* ``sync``: :class:`~torchrl_stages.GymStageEnv`, gymnasium's ``SyncVectorEnv`` (the default);
* ``async``: the same with ``vectorize="async"`` (``AsyncVectorEnv``, one worker process per
  copy).

Envs: CartPole-v1 (classic control, a step of microseconds) and a MiniGrid level as the
``minigrid`` task runs it (``StagedMiniGrid``, a step of tens of microseconds).

    python scripts/benchmark_gym_vector.py --envs 8 64 --steps 400 --out results/vector
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time
from pathlib import Path

import gymnasium
import torch
from _benchmark import add_table_argument, command_line, machine_speed, save_table, speed_note
from torchrl.envs import GymEnv, GymWrapper, SerialEnv

from torchrl_stages import GymStageEnv, threshold_stage
from torchrl_stages.envs.minigrid import MiniGridEnv, StagedMiniGrid, import_minigrid

MINIGRID = "MiniGrid-DoorKey-8x8-v0"
WAYS = ("serial", "sync", "async")


def _serial_minigrid(env_id: str) -> GymWrapper:
    """One copy of the staged MiniGrid level (an element of the ``serial`` way)."""
    return GymWrapper(StagedMiniGrid(gymnasium.make(env_id)), categorical_action_encoding=True)


def build(env_id: str, way: str, n: int):
    """``n`` copies of ``env_id`` stepped ``way``."""
    if env_id == "CartPole-v1":
        if way == "serial":
            return SerialEnv(n, functools.partial(GymEnv, env_id, categorical_action_encoding=True))
        stage = functools.partial(threshold_stage, thresholds=[0.0], index=2)
        return GymStageEnv(env_id, stage, num_stages=2, vectorize=way, batch_size=(n,))
    if way == "serial":
        return SerialEnv(n, functools.partial(_serial_minigrid, env_id))
    return MiniGridEnv(env_id, vectorize=way, batch_size=(n,))


def frames_per_second(env, steps: int) -> float:
    env.set_seed(0)
    td = env.reset()
    for _ in range(20):  # warm-up
        td["action"] = env.action_spec.rand()
        _, td = env.step_and_maybe_reset(td)
    start = time.perf_counter()
    for _ in range(steps):
        td["action"] = env.action_spec.rand()
        _, td = env.step_and_maybe_reset(td)
    return env.batch_size[0] * steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[8, 64])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("results/vector"))
    add_table_argument(parser)
    args = parser.parse_args()
    import_minigrid()
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    speed = machine_speed()
    rows = []
    header = [
        "| env | copies | " + " | ".join(f"{w} (frames/s)" for w in WAYS) + " | sync / serial |"
    ]
    header.append("|---|---|" + "---|" * (len(WAYS) + 1))
    lines = []
    print("\n".join(header), flush=True)
    for env_id in ("CartPole-v1", MINIGRID):
        for n in args.envs:
            fps = {}
            for way in WAYS:
                env = build(env_id, way, n)
                try:  # the ways alternate within each repeat (the machine drifts)
                    fps[way] = [frames_per_second(env, args.steps) for _ in range(args.repeats)]
                finally:
                    env.close()
            median = {way: statistics.median(v) for way, v in fps.items()}
            rows.append({"env": env_id, "copies": n, "fps": fps})
            cells = [f"{median[w]:,.0f}" for w in WAYS]
            lines.append(
                f"| {env_id} | {n} | "
                + " | ".join(cells)
                + f" | {median['sync'] / median['serial']:.1f}x |"
            )
            print(lines[-1], flush=True)
    note = speed_note(speed, machine_speed())
    (args.out / "rows.json").write_text(json.dumps(rows, indent=2))
    table = ["```text", f"$ {command_line()}", "```", "", *header, *lines, "", note]
    save_table(args.out, table, args.table)
    print(note)
    print(f"wrote {args.out / 'table.md'}")


if __name__ == "__main__":
    main()
