"""Stage store benchmark: a sweep over stage 0's learning rate with and without ``stage_store``.

For each discount preset, the sweep ``stages-train -m task.stages.s0.lr=1e-3,2e-3,3e-3,5e-3``
runs twice on the 5-stage grid world, one launch after the other (Hydra's basic launcher, one
job at a time): without a stage store every job trains all five stages; with one, the first job
trains them and the other three reuse stages 1-4 and train stage 0 only. Table: per job, the
whole-task results of both sweeps, the stages reused and whether every stage file's weights are
bitwise equal; the wall-clock of each sweep and their ratio.

    python scripts/benchmark_stage_store.py --out results/stage_store [--presets homo hetero] \
        [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import torch
from _benchmark import add_table_argument, command_line, machine_speed, save_table, speed_note

LRS = ("1e-3", "2e-3", "3e-3", "5e-3")


def sweep(
    out: Path, preset: str, lrs: list[str], store: Path | None, overrides: list[str]
) -> float:
    """Runs the sweep into ``out``; returns its wall-clock in seconds."""
    argv = [
        str(Path(sys.executable).with_name("stages-train")),
        "-m",
        f"task.stages.s0.lr={','.join(lrs)}",
        f"task/gammas={preset}",
        f"hydra.sweep.dir={out}",
        "progress=false",
        *([f"stage_store={store}"] if store is not None else []),
        *overrides,
    ]
    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{done.stderr[-3000:]}")
    return seconds


def same_weights(a: Path, b: Path) -> bool:
    """Whether every stage file of the two job directories holds the same tensors."""
    files = sorted(p.name for p in a.glob("stage_*.pt"))
    if not files or files != sorted(p.name for p in b.glob("stage_*.pt")):
        return False
    for name in files:
        wa = torch.load(a / name, weights_only=True)["model"]
        wb = torch.load(b / name, weights_only=True)["model"]
        if wa.keys() != wb.keys() or not all(torch.equal(wa[k], wb[k]) for k in wa):
            return False
    return True


def result(job: Path) -> dict:
    data = json.loads((job / "eval.json").read_text())
    metrics = data.get("task_metrics", {})
    return {
        "success": data["success_rate"],
        "steps": data["mean_steps"],
        "value_error": metrics.get("value_map_max_abs_error"),
        "reused": sorted(data["training"].get("reused", {})),
    }


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["homo", "hetero"])
    parser.add_argument("--lrs", nargs="+", default=list(LRS), help="stage 0's learning rates")
    parser.add_argument("--out", type=Path, default=Path("results/stage_store"))
    add_table_argument(parser)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every job")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    command = command_line()
    print(command, flush=True)
    speed = machine_speed()
    lines = [
        "| preset | s0 lr | success (no store / store) | max abs V error (no store / store) | "
        "stages reused | bitwise equal |",
        "|---|---|---|---|---|---|",
    ]
    notes, rows = [], []
    for preset in args.presets:
        plain_dir, store_dir = args.out / f"{preset}_plain", args.out / f"{preset}_store"
        plain_s = sweep(plain_dir, preset, args.lrs, None, args.overrides)
        store_s = sweep(store_dir, preset, args.lrs, args.out / f"store_{preset}", args.overrides)
        for job, lr in enumerate(args.lrs):
            a, b = result(plain_dir / str(job)), result(store_dir / str(job))
            equal = same_weights(plain_dir / str(job), store_dir / str(job))
            equal_results = {**a, "reused": []} == {**b, "reused": []}
            rows.append({"preset": preset, "lr": lr, "plain": a, "store": b, "bitwise": equal})
            lines.append(
                f"| {preset} | {lr} | {a['success']:.0%} / {b['success']:.0%} | "
                f"{_num(a['value_error'])} / {_num(b['value_error'])} | "
                f"{', '.join(b['reused']) or 'none'} | "
                f"{'yes' if equal and equal_results else 'NO'} |"
            )
            print(lines[-1], flush=True)
        notes.append(
            f"- {preset}: sweep of {len(args.lrs)} jobs {plain_s:.0f} s without the store, "
            f"{store_s:.0f} s with it: {plain_s / store_s:.2f}x faster"
        )
        (args.out / "rows.json").write_text(json.dumps(rows, indent=2))
    notes.append("- Hydra's basic launcher: the jobs of a sweep run one after another")
    notes.append(speed_note(speed, machine_speed()))
    table = ["```text", f"$ {command}", "```", "", *lines, "", *notes]
    save_table(args.out, table, args.table)
    print("\n".join(table))
    if not all(r["bitwise"] for r in rows):
        raise SystemExit("a job with the stage store differs from the same job without it")


if __name__ == "__main__":
    main()
