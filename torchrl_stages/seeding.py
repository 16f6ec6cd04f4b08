"""The seeding rule: which generator seeds build and drive each part of a run. For seed ``s``
(the first of several sharing envs): stage ``k``'s generator and training env ``s + k``, its
evaluation env ``+ EVAL_OFFSET``; the whole-task evaluation and probe ``s + TASK_EVAL_OFFSET``."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import torch

from torchrl_stages.learners import Learner
from torchrl_stages.learners.stacking import stack_learners

T = TypeVar("T")

#: what the evaluation env's seed adds to the training env's
EVAL_OFFSET = 10_000
#: what the whole-task evaluation's seed adds to the run's
TASK_EVAL_OFFSET = 20_000


def stage_seed(seed: int, stage: int) -> int:
    """The seed of stage ``stage``'s generator and training env."""
    return seed + stage


def phase_seed(seed: int, stage: int) -> int:
    """The global generator's seed at the start of the joint phase from stage ``stage``."""
    return seed + 1000 * (stage + 1)


def seeded(
    make: Callable[..., Learner], seeds: Sequence[int], offset: int, envs: Callable[[], T]
) -> tuple[Learner, T]:
    """A stage's learner (``make``) and envs (``envs()``), after ``torch.manual_seed(seeds[0] +
    offset)``. Several seeds' learner is built first, row ``i`` holding what ``make()`` builds
    right after ``torch.manual_seed(seeds[i] + offset)``."""
    learner = None
    if len(seeds) > 1:
        singles = []
        for seed in seeds:
            torch.manual_seed(seed + offset)
            singles.append(make())
        learner = stack_learners(make(seeds=len(seeds)), singles)
    torch.manual_seed(seeds[0] + offset)
    built = envs()
    return make() if learner is None else learner, built
