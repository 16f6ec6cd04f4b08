"""Statistics across seeds on rliable (Agarwal et al., 2021): mean, interquartile mean and
performance profiles with seeded stratified-bootstrap confidence intervals."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from torchrl_stages.sweeps.jobs import Job, configs, result_metrics

#: bootstrap resamples (rliable's default is 50 000: these intervals are for a summary)
REPS = 2000


def finished_scores(jobs: Sequence[Job], config: str, metric: str) -> np.ndarray:
    """The finished runs' values as rliable's ``(runs, tasks)`` array, one task."""
    done = (j.metrics.get(metric) for j in jobs if j.config == config and j.status == "done")
    return np.asarray([v for v in done if v is not None], dtype=float).reshape(-1, 1)


def interval_estimates(scores: np.ndarray, func, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``func(scores)`` and its stratified-bootstrap interval (``(2, len)``). rliable draws from
    numpy's global generator (it ignores ``random_state``): seeded for the call, then restored."""
    from rliable import library as rly  # here: ~1 s of imports that training never needs

    state, absl = np.random.get_state(), logging.getLogger("absl")
    level = absl.level
    absl.setLevel(logging.WARNING)  # rliable logs a line per estimate (through absl)
    np.random.seed(seed)
    try:
        points, intervals = rly.get_interval_estimates(
            {"x": scores}, func, reps=REPS, confidence_interval_size=0.95
        )
    finally:
        np.random.set_state(state)
        absl.setLevel(level)
    return np.asarray(points["x"]), np.asarray(intervals["x"])


@dataclass
class Aggregate:
    """One metric of one configuration across its finished seeds: mean and IQM with intervals.

    Examples:
        >>> Aggregate("lr=1e-3", "success_rate", 3, 1, 0.5, 0.25, 0.75, 0.5, 0.0, 1.0).ci_high
        0.75
    """

    config: str
    metric: str
    n: int  # finished jobs with a value
    failed: int  # jobs of the configuration that did not finish
    mean: float | None
    ci_low: float | None
    ci_high: float | None
    iqm: float | None
    iqm_low: float | None
    iqm_high: float | None


def _mean_and_iqm(scores: np.ndarray) -> np.ndarray:
    """rliable's ``aggregate_mean`` and ``aggregate_iqm`` in one sort (called ``REPS`` times)."""
    ordered = np.sort(scores, axis=None)
    cut = int(0.25 * ordered.size)
    return np.array([ordered.mean(), ordered[cut : ordered.size - cut].mean()])


def aggregate_jobs(jobs: Sequence[Job], seed: int = 0) -> list[Aggregate]:
    """The :class:`Aggregate` of each metric of each configuration."""
    out = []
    for config in configs(jobs):
        failed = sum(j.status != "done" for j in jobs if j.config == config)
        for metric in result_metrics(jobs):
            scores, numbers = finished_scores(jobs, config, metric), [None] * 6
            if scores.size:
                point, interval = interval_estimates(scores, _mean_and_iqm, seed)
                numbers = map(float, [point[0], *interval[:, 0], point[1], *interval[:, 1]])
            out.append(Aggregate(config, metric, len(scores), failed, *numbers))
    return out


def performance_profiles(
    jobs: Sequence[Job], taus: np.ndarray, seed: int = 0
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per configuration, the fraction of its runs with a success rate above each of ``taus``
    (rliable's score distribution) and its bootstrap interval."""

    def profile(scores: np.ndarray) -> np.ndarray:
        # rliable's score_distributions, every tau at once (it loops with np.vectorize)
        return (scores.reshape(1, -1) > taus.reshape(-1, 1)).mean(axis=1)

    scores = {config: finished_scores(jobs, config, "success_rate") for config in configs(jobs)}
    return {config: interval_estimates(s, profile, seed) for config, s in scores.items() if s.size}
