"""A stage's greedy evaluations over its training, read back from run directories.

Every stage evaluation logs ``eval/stage_<k>/<metric>`` to the run's ``metrics.csv`` (success
rate, mean steps, discounted return, value error, ...). This prints them as one Markdown table
per stage: a row per evaluation (frames of the stage), a column per run and metric, so that
"when did this stage learn, and does it still improve at the end of its budget" is read off the
runs a benchmark already made.

    python scripts/stage_evaluations.py RUN_DIR [RUN_DIR ...] [--stage K ...]
        [--metrics success_rate mean_steps discounted_return]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchrl_stages.plots import Series, read_stage_metrics
from torchrl_stages.runs.layout import METRICS_FILE

DEFAULT_METRICS = ("success_rate", "mean_steps", "discounted_return", "value_error")


def evaluation_table(runs: dict[str, dict[int, Series]], stage: int, metrics: list[str]) -> str:
    """The Markdown table of ``stage``'s evaluations in ``runs`` (name -> its metrics, as
    :func:`~torchrl_stages.plots.read_stage_metrics` reads them)."""
    columns: list[tuple[str, str]] = []
    values: dict[tuple[str, str], dict[float, float]] = {}
    for name, stages in runs.items():
        series = stages.get(stage, {})
        for metric in metrics:
            points = series.get(("eval", "stage", metric))
            if points:
                columns.append((name, metric))
                values[(name, metric)] = dict(points)
    if not columns:
        return f"stage {stage}: no evaluations of {', '.join(metrics)} in these runs"
    frames = sorted({f for column in columns for f in values[column]})
    lines = [
        "| frames | " + " | ".join(f"{name} {metric}" for name, metric in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for f in frames:
        cells = [f"{values[c][f]:.3g}" if f in values[c] else "" for c in columns]
        lines.append(f"| {int(f)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (or metrics.csv)")
    parser.add_argument("--stage", type=int, nargs="+", default=None, help="default: every stage")
    parser.add_argument("--metrics", nargs="+", default=list(DEFAULT_METRICS))
    args = parser.parse_args()
    runs: dict[str, dict[int, Series]] = {}
    for run in args.runs:
        path = run if run.is_file() else run / METRICS_FILE
        if not path.is_file():
            print(f"error: {path} does not exist (is {run} a run directory?)", file=sys.stderr)
            return 2
        runs[run.parent.name if run.is_file() else run.name] = read_stage_metrics(path)
    stages = args.stage
    if stages is None:
        stages = sorted({k for series in runs.values() for k in series})
    for stage in stages:
        print(f"stage {stage}\n\n{evaluation_table(runs, stage, args.metrics)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
