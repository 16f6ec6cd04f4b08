"""``stages-tune``: hyper-parameter tuning with Optuna, each trial a ``stages-train`` run: the
search space (:mod:`~torchrl_stages.tune.space`), checks before any trial runs
(:mod:`~torchrl_stages.tune.checks`), pruning on the stages' evaluations
(:mod:`~torchrl_stages.tune.pruning`) and the study (:mod:`~torchrl_stages.tune.study`); its
Hydra app is ``stages-tune`` in :mod:`torchrl_stages.cli`. Optuna is imported only when a
study runs: this package loads without the ``[tune]`` extra."""

from torchrl_stages.tune.pruning import TrialPruning
from torchrl_stages.tune.space import ParamSpec, hydra_value, search_space, train_overrides
from torchrl_stages.tune.study import StudyContext, StudyError, run_study

__all__ = [
    "ParamSpec",
    "StudyContext",
    "StudyError",
    "TrialPruning",
    "hydra_value",
    "run_study",
    "search_space",
    "train_overrides",
]
