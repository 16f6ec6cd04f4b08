"""Runs: what a training launch is and leaves on disk, one job per module."""

from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.layout import RunDirError, seed_dir
from torchrl_stages.runs.loading import LoadedRun, load_policy, load_run

__all__ = [
    "Experiment",
    "LoadedRun",
    "RunDir",
    "RunDirError",
    "load_policy",
    "load_run",
    "seed_dir",
]
