"""One stage's gradient update in isolation: its first call and its steady-state cost, per
``compile`` mode.

``profile_stage.py`` times updates inside a training run, where a learner's compilation is part
of the update phase. Here each stage's learner updates on one replay batch of its own env
(collected as the stage loop collects its first batch) once, then ``--warmup`` times, then
``--updates`` times, synchronised with the device, so that the one-off cost and the per-update
cost are read apart. The first call is the loss's compilation with ``compile`` on (for TD3 the
critic's only: its actor loss runs from the second update, ``policy_update_delay``) and lazy
set-up (optimizer state, CUDA libraries) with ``compile=off``; ``reduce-overhead`` records its
CUDA graphs on the second call, in the warm-up. An update includes its target update (timed
apart in ``profile_stage.py``).

``--seeds 10`` also times learners of 10 seeds stacked (as ``seeds=[...]`` trains them), each
seed on its own batch: the cost per seed and update, against the single learner's, is what
stacking saves. With ``compile=off`` each row counts an update's floating-point operations
(``torch.utils.flop_counter``: the matrix products, forward and backward) and gives the rate
it ran at, in GFLOP/s: how close an update is to the CPU's arithmetic limit.

    python scripts/profile_update.py [OVERRIDE ...] --stages gridworld:4 cargo:0
        [--compile off default reduce-overhead] [--seeds 2 10] [--updates 200]

Each ``TASK:STAGE`` is built from the task's config with the overrides (``device=cuda`` for the
GPU); a stage below the last reads an untrained next-stage value (its cost does not depend on
the values).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from _benchmark import (
    add_table_argument,
    command_line,
    compose_config,
    machine_speed,
    save_table,
    speed_note,
)
from tensordict import TensorDictBase
from torch.utils.flop_counter import FlopCounterMode

from torchrl_stages.collector import StageCollector
from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS, Learner, make_learner
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.runs.experiment import build_task, compile_mode
from torchrl_stages.task import StagedTask

MODES = ("auto", "off", "default", "reduce-overhead", "max-autotune")


def synchronize(device: torch.device) -> None:
    """Waits for the device's queued work (a GPU's; nothing to wait for on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def replay_batch(
    task: StagedTask, stage: int, learner: Learner, samples: int = 1
) -> TensorDictBase:
    """``samples`` replay samples of ``stage``'s first collected batch, as its stage loop
    draws one, concatenated."""
    cfg = task.stage_cfg(stage)
    next_value = None
    if stage < task.num_stages - 1:
        nxt = make_learner(task.stage_cfg(stage + 1), task.specs(stage + 1), device=task.device)
        next_value = nxt.value()
    env = task.stage_env(stage, cfg.num_envs, next_value)
    collector = StageCollector(
        env,
        learner.exploration_policy,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=cfg.frames_per_batch,
        init_random_frames=cfg.init_random_frames,
    )
    batch = next(iter(collector))
    buffer = SeedReplayBuffer(cfg.buffer_size, num_seeds=1, device=learner.device)
    buffer.extend(batch.select(*learner.loss.in_keys, strict=False))
    return buffer.sample(cfg.batch_size * samples)[0]


def update_flops(learner: Learner, batch: TensorDictBase) -> int:
    """The floating-point operations of one update of ``learner`` on ``batch`` (its matrix
    products, forward and backward, as ``torch.utils.flop_counter`` counts them)."""
    with FlopCounterMode(display=False) as counter:
        learner.update(batch)
    return counter.get_total_flops()


def profile(
    spec: str, mode: str, overrides: list[str], updates: int, warmup: int, seeds: int | None
) -> dict[str, Any]:
    """Times the update of ``spec`` (``TASK:STAGE``) under ``compile=mode`` (``seeds``: that
    many seeds stacked in one learner, each on its own batch); returns its row."""
    task_name, stage = spec.split(":")
    stage = int(stage)
    cfg = compose_config(task_name, *overrides, f"compile={mode}")
    mode = compile_mode(cfg)  # auto resolved for the device
    torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.seed))
    torch._dynamo.reset()
    task = build_task(cfg)
    learner = make_learner(task.stage_cfg(stage), task.specs(stage), mode, task.device)
    device = learner.device
    batch = replay_batch(task, stage, learner, seeds or 1)
    if seeds is not None:  # seed-major [seeds, batch_size], as a seeds trainer samples
        batch = batch.reshape(seeds, -1)
        learner = make_learner(
            task.stage_cfg(stage), task.specs(stage), mode, task.device, seeds=seeds
        )
    synchronize(device)
    start = time.perf_counter()
    learner.update(batch)
    synchronize(device)
    first = time.perf_counter() - start
    for _ in range(warmup):
        learner.update(batch)
    synchronize(device)
    start = time.perf_counter()
    for _ in range(updates):
        learner.update(batch)
    synchronize(device)
    per_update = (time.perf_counter() - start) / updates
    flops = update_flops(learner, batch) if mode == "off" else None  # compiled: not counted
    return {
        "task": task_name,
        "stage": stage,
        "algo": learner.algo,
        "compile": mode,
        "device": str(device),
        "seeds": seeds,
        "batch_size": int(batch.batch_size[-1]),
        "first_call_s": first,
        "ms_per_update": per_update * 1e3,
        "updates_per_s": 1.0 / per_update,
        "ms_per_seed_update": per_update * 1e3 / (seeds or 1),
        "gflops_per_s": None if flops is None else flops / per_update / 1e9,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--stages", nargs="+", default=["gridworld:4", "cargo:0", "manipulator:0"])
    parser.add_argument(
        "--compile", nargs="+", default=["off", "reduce-overhead"], help=f"modes among {MODES}"
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=None,
        help="also time learners of that many seeds stacked (seeds=[...]), each on its own batch",
    )
    parser.add_argument("--updates", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    add_table_argument(parser)
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    misplaced = [word for word in (*args.stages, *args.compile) if "=" in word]
    if misplaced:  # --stages and --compile take every word after them
        parser.error(f"{misplaced} are Hydra overrides: put them before --stages and --compile")
    unknown = [mode for mode in args.compile if mode not in MODES]
    if unknown:
        parser.error(f"--compile {unknown}: not compile modes; choose among {list(MODES)}")
    malformed = [spec for spec in args.stages if not re.fullmatch(r"[\w-]+:\d+", spec)]
    if malformed:
        parser.error(f"--stages {malformed}: each is TASK:STAGE, e.g. gridworld:4 or cargo:0")
    if any(word.split("=")[0].lstrip("+") == "compile" for word in args.overrides):
        parser.error("set the compile modes with --compile, not a compile= override")
    register_configs(ALGORITHMS)
    out = args.out or Path(tempfile.mkdtemp(prefix="profile_update_"))
    out.mkdir(parents=True, exist_ok=True)
    command = command_line()
    gpu = f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ""
    machine = f"torch {torch.__version__}, {os.cpu_count()} CPUs{gpu}"
    print(f"{command}\n{machine}", flush=True)
    speed = machine_speed()
    header = ["task", "stage", "algo", "seeds", "compile", "first call (s)", "ms per update"]
    header += ["updates/s", "ms per seed and update", "GFLOP/s"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    rows = []
    for spec in args.stages:
        for seeds, mode in itertools.product([None, *(args.seeds or [])], args.compile):
            row = profile(spec, mode, args.overrides, args.updates, args.warmup, seeds)
            rows.append(row)
            cells = [row["task"], str(row["stage"]), row["algo"], str(seeds or "-"), mode]
            cells += [f"{row['first_call_s']:.1f}", f"{row['ms_per_update']:.2f}"]
            cells += [f"{row['updates_per_s']:.0f}", f"{row['ms_per_seed_update']:.2f}"]
            gflops = row["gflops_per_s"]
            cells.append("-" if gflops is None else f"{gflops:.1f}")
            lines.append("| " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
            (out / "rows.json").write_text(json.dumps(rows, indent=2))
    note = speed_note(speed, machine_speed())
    print(note)
    table = ["```text", f"$ {command}", "```", "", *lines, "", f"- {machine}", note]
    save_table(out, table, args.table)
    print(f"wrote {out / 'rows.json'} and {out / 'table.md'}")


if __name__ == "__main__":
    main()
