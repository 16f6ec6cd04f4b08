"""Runs: what a training launch is and leaves on disk, one job per module.

:class:`Experiment` trains one seed or several (:mod:`~torchrl_stages.runs.experiment`), each
seed's directory a :class:`SeedRun` (:mod:`~torchrl_stages.runs.seed_run`) that keeps its
stages through a :class:`RunKeeper` (:mod:`~torchrl_stages.runs.keeper`). On disk: the layout
(:mod:`~torchrl_stages.runs.layout`), the directory and its record
(:mod:`~torchrl_stages.runs.directory`, its lock :mod:`~torchrl_stages.runs.lock`), what a run
directory may make the package do (:mod:`~torchrl_stages.runs.trust`), reading a finished run
back (:mod:`~torchrl_stages.runs.loading`), its whole-task evaluation
(:mod:`~torchrl_stages.runs.evaluation`), the export of its policy
(:mod:`~torchrl_stages.runs.export`) and the store of finished stages that runs share
(:mod:`~torchrl_stages.runs.stage_store`).
"""

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
