"""The names of a run directory's files, and the error a run directory raises."""

from __future__ import annotations

from pathlib import Path

EVAL_FILE = "eval.json"
CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
STATUS_FILE = "status.json"
CHECKPOINTS = "checkpoints"
RECORD_FILE = "run.json"  # in .stages/
#: names of a run's files: a directory holding any of them (or a stage file) holds a run
RUN_MARKERS = (CONFIG_FILE, EVAL_FILE, METRICS_FILE, CHECKPOINTS)
#: what runs written without a record hold (adopted when such a run is resumed)
LEGACY_ENTRIES = (*RUN_MARKERS, STATUS_FILE, "csv", ".hydra")
#: the figures and arrays a run's report writes at its top level (adopted with it)
REPORT_FILES = ("*.png", "*.npy")
RECORD_FORMAT = "torchrl-stages run"
SEED_CHECKPOINTS = "seed_checkpoints"


def seed_dir(run_dir: str | Path, seed: int) -> Path:
    return Path(run_dir) / f"seed_{seed}"


class RunDirError(RuntimeError):
    """A run directory cannot be used as asked (held, damaged, foreign or untrusted)."""
