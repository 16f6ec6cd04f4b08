"""The seeding rule: which generator seeds build and drive each part of a run, in one place.

For seed ``s`` (the first of a run's seeds when several share its envs):

- a backward stage ``k``: the global generator and the training env ``s + k``, the
  evaluation env ``s + 10_000 + k`` (:data:`EVAL_OFFSET`);
- the flat learner: the same with ``k = 0``;
- a joint phase from stage ``k``: the global generator ``s + 1000 * (k + 1)``
  (:func:`phase_seed`), the training env ``s + k``, the evaluation env ``s + 10_000 + k``;
  the learners of every stage are built once, right after ``torch.manual_seed(s)``;
- the whole-task evaluation and the probe: ``s + 20_000`` (:data:`TASK_EVAL_OFFSET`).

A stage's learner of one seed is built after its envs, from the generator they were built
with; with several seeds, seed ``s``'s row holds the weights ``make()`` builds right after
``torch.manual_seed(s + k)`` (:func:`seed_learner`), and the envs, built after them, draw
from the first seed's streams. A seed's run among others is thus a draw from the same
distribution as its run alone, not the same bits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import torch

from torchrl_stages.learners import Learner
from torchrl_stages.learners.stacking import stack_learners

__all__ = [
    "EVAL_OFFSET",
    "TASK_EVAL_OFFSET",
    "phase_seed",
    "seed_learner",
    "seeded",
    "stage_seed",
]

T = TypeVar("T")

#: what the evaluation env's seed adds to the training env's
EVAL_OFFSET = 10_000
#: what the whole-task evaluation's seed adds to the run's
TASK_EVAL_OFFSET = 20_000


def stage_seed(seed: int, stage: int) -> int:
    """The seed of stage ``stage``'s generator and training env (its evaluation env:
    ``+ EVAL_OFFSET``)."""
    return seed + stage


def phase_seed(seed: int, stage: int) -> int:
    """The global generator's seed at the start of the joint phase from stage ``stage``."""
    return seed + 1000 * (stage + 1)


def seed_learner(make: Callable[..., Learner], seeds: Sequence[int], offset: int = 0) -> Learner:
    """``make(seeds=len(seeds))`` holding, in row ``i``, the initial weights of ``make()``
    built right after ``torch.manual_seed(seeds[i] + offset)`` (those of a run of that seed
    alone, when building its envs draws nothing from the global generator)."""
    singles = []
    for seed in seeds:
        torch.manual_seed(seed + offset)
        singles.append(make())
    return stack_learners(make(seeds=len(seeds)), singles)


def seeded(
    make: Callable[..., Learner],
    seeds: Sequence[int],
    offset: int,
    envs: Callable[[], T],
) -> tuple[Learner, T]:
    """A stage's learner (``make``) and envs (``envs()``) by the rule: the global generator
    seeded with ``seeds[0] + offset``, then the envs; then, for one seed, its learner; for
    several, :func:`seed_learner` built before the envs."""
    if len(seeds) == 1:
        torch.manual_seed(seeds[0] + offset)
        built = envs()
        return make(), built
    learner = seed_learner(make, seeds, offset)
    torch.manual_seed(seeds[0] + offset)
    return learner, envs()
