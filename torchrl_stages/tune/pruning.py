"""Optuna's side of a study: stage evaluations reported to the trial (:class:`TrialPruning`),
the sampler and the pruner."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from torchrl_stages.loggers import StopRun
from torchrl_stages.metric_names import is_loop_evaluation


class TrialPruning:
    """A run's :data:`~torchrl_stages.loggers.Observer` that reports each loop evaluation's
    success rate to an Optuna ``trial`` (step: the evaluation's index in the run; the failure
    rate when the objective is minimized) and raises ``StopRun("pruned")`` when it should stop.

    Examples:
        >>> class Trial:  # what it uses of an optuna.Trial
        ...     reported = []
        ...     def report(self, value, step):
        ...         self.reported.append((step, value))
        ...     def should_prune(self):
        ...         return len(self.reported) >= 2
        >>> trial = Trial()
        >>> pruning = TrialPruning(trial)
        >>> pruning({"eval/stage_4/success_rate": 0.5, "eval/stage_4/value_error": 0.1}, 512)
        >>> pruning({"train/stage_4/loss": 0.2}, 768)  # not an evaluation
        >>> pruning({"eval/stage_4/success_rate": 0.25}, 1024)
        Traceback (most recent call last):
        ...
        torchrl_stages.loggers.StopRun: pruned at stage evaluation 1 (...=0.25 at 1024 frames ...)
        >>> trial.reported
        [(0, 0.5), (1, 0.25)]
    """

    def __init__(self, trial: Any, direction: str = "maximize") -> None:
        self.trial = trial
        self.minimize = direction == "minimize"
        self.evaluations = 0

    def __call__(self, metrics: dict[str, float], step: int) -> None:
        for name, value in metrics.items():
            if not is_loop_evaluation(name):
                continue
            index, self.evaluations = self.evaluations, self.evaluations + 1
            success = float(value)
            self.trial.report(1.0 - success if self.minimize else success, index)
            if self.trial.should_prune():
                raise StopRun(
                    "pruned",
                    f"pruned at stage evaluation {index} ({name}={success:g} at {step} frames "
                    "of the stage)",
                )


def make_sampler(name: str, seed: int) -> Any:
    """The seeded Optuna sampler ``tune.sampler`` names."""
    import optuna

    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed)


def make_pruner(tune: DictConfig, direction: str) -> Any:
    """The Optuna pruner ``tune.pruner`` names, over what :class:`TrialPruning` reports."""
    import optuna

    warmup = int(tune.warmup_steps)
    if tune.pruner == "median":
        return optuna.pruners.MedianPruner(
            n_startup_trials=int(tune.startup_trials), n_warmup_steps=warmup
        )
    if tune.pruner == "threshold":
        below = float(tune.prune_below)
        if direction == "minimize":  # failure rates reported: above 1 - below is pruned
            return optuna.pruners.ThresholdPruner(upper=1.0 - below, n_warmup_steps=warmup)
        return optuna.pruners.ThresholdPruner(lower=below, n_warmup_steps=warmup)
    return optuna.pruners.NopPruner()
