"""``stages-tune``: hyper-parameter tuning with Optuna, each trial a ``stages-train`` run. Optuna
is imported only when a study runs: the package loads without the ``[tune]`` extra."""

from torchrl_stages.tune.study import StudyContext, StudyError, TrialPruning, run_study

__all__ = ["StudyContext", "StudyError", "TrialPruning", "run_study"]
