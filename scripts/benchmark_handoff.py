"""Handoff diagnostics of the shipped tasks, and a grid world whose stage starts miss the
handoff states.

Each run is ``stages-train task=<task>`` with the task's defaults (seed 0); its whole-task
evaluation measures, at every boundary k -> k+1, the error of ``V_{k+1}`` at the states where
the episodes entered stage k+1 against the return obtained after them, and the share of those
states outside stage k+1's training starts. The variant ``gridworld_missed`` starts every stage
in rows 13-24 only (``+task.env.stage_start_rows=[13,25]``) while the whole-task episodes start
on every row of column 0: the diagnostic must flag it. Writes ``table.md``, ``rows.json`` and
each run's ``handoff.png`` as ``handoff_<variant>.png`` (``--figures``: also there).

    python scripts/benchmark_handoff.py --out results/handoff --figures docs
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from _benchmark import (
    add_table_argument,
    command_line,
    machine_speed,
    save_table,
    speed_note,
    train,
)

from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS

VARIANTS = {
    "gridworld": ("gridworld", []),
    "gridworld_missed": ("gridworld", ["+task.env.stage_start_rows=[13,25]"]),
    "manipulator": ("manipulator", []),
    "cargo": ("cargo", []),
}


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("results/handoff"))
    add_table_argument(parser)
    parser.add_argument("--figures", type=Path, default=None, help="also copy the figures here")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = parser.parse_args()
    register_configs(ALGORITHMS)
    args.out.mkdir(parents=True, exist_ok=True)
    command = command_line()
    print(command, flush=True)
    speed = machine_speed()
    lines = [
        "| run | success | boundary | episodes | mean abs(V - G) | mean V - G | "
        "outside starts | flagged |",
        "|---|---|---|---|---|---|---|---|",
    ]
    rows = []
    for variant in args.variants:
        task, extra = VARIANTS[variant]
        run_dir = args.out / variant
        shutil.rmtree(run_dir, ignore_errors=True)
        result = train(
            task, run_dir, f"seed={args.seed}", "progress=false", *extra, *args.overrides
        )
        rows.append({"variant": variant, "success": result["success_rate"], **result})
        for r in result.get("handoff", []):
            lines.append(
                f"| {variant} | {result['success_rate']:.1%} | {r['boundary']} | {r['episodes']} | "
                f"{_num(r.get('value_error_mean'), '.4f')} | {_num(r.get('value_bias'), '+.4f')} | "
                f"{_num(r.get('outside_starts'), '.0%')} | "
                f"{'yes' if r.get('extrapolated') else 'no'} |"
            )
            print(lines[-1], flush=True)
        figure = run_dir / "handoff.png"
        if figure.is_file():
            for where in [args.out, args.figures] if args.figures else [args.out]:
                where.mkdir(parents=True, exist_ok=True)
                shutil.copy(figure, where / f"handoff_{variant}.png")
        (args.out / "rows.json").write_text(
            json.dumps(
                [{"variant": r["variant"], "handoff": r.get("handoff")} for r in rows], indent=2
            )
        )
    notes = [
        f"- seed {args.seed}; each task's own defaults; whole-task episodes as in its eval.json",
        "- outside starts: share of handoff states farther from stage k+1's training starts than "
        "95% of held-out starts are (states drawn like the starts: 5%, or 0% when the starts are "
        "finitely many); flagged above 25%",
        speed_note(speed, machine_speed()),
    ]
    table = ["```text", f"$ {command}", "```", "", *lines, "", *notes]
    save_table(args.out, table, args.table)
    print("\n".join(table))


if __name__ == "__main__":
    main()
