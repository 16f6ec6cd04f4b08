"""What a run directory holds, by name, and the error a run directory raises.

A run directory holds ``config.yaml`` (the resolved config), ``stage_<k>.pt`` for every
finished stage, ``checkpoints/`` for the stage in progress, ``metrics.csv``, ``eval.json``,
figures, ``status.json`` when a run did not finish, and ``.stages/``: the run's record
(``run.json``) and the lock that keeps a second process out. A launch of several seeds keeps
each seed's run in ``seed_<s>/`` and their common checkpoints in ``seed_checkpoints/``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["EVAL_FILE", "RunDirError", "seed_dir"]

EVAL_FILE = "eval.json"
CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
STATUS_FILE = "status.json"
CHECKPOINTS = "checkpoints"
RECORD_FILE = "run.json"  # in .stages/
#: names of a run's files: a directory holding any of them (or a stage file) holds a run
RUN_MARKERS = (CONFIG_FILE, EVAL_FILE, METRICS_FILE, CHECKPOINTS)
#: what runs of versions without a record wrote (adopted when such a run is resumed)
LEGACY_ENTRIES = (*RUN_MARKERS, STATUS_FILE, "csv", ".hydra")
LEGACY_PATTERNS = ("stage_*.pt",)
#: the figures earlier versions wrote (the shipped tasks' reports and the learning curves)
LEGACY_FIGURES = (
    "learning_curves.png",
    "trajectories.png",
    "value_map.png",
    "value_map.npy",
    "manipulator.png",
    "cargo.png",
)
RECORD_FORMAT = "torchrl-stages run"
#: where the checkpoints of a launch of several seeds live, beside the seeds' directories
SEED_CHECKPOINTS = "seed_checkpoints"


def seed_dir(run_dir: str | Path, seed: int) -> Path:
    """Where seed ``seed`` of a launch of several seeds in ``run_dir`` lives."""
    return Path(run_dir) / f"seed_{seed}"


class RunDirError(RuntimeError):
    """A run directory cannot be used as asked: it already holds a run, another process holds
    it, a file in it is damaged or foreign, or its config names code it may not run."""
