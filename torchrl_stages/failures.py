"""How a stage's training fails: non-finite env data (:class:`EnvError`) or divergence."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from functools import partial
from typing import Any

from tensordict.utils import NestedKey

from torchrl_stages.learners import Learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.transforms import NonFiniteInputError, NonFiniteValueError

#: the exit codes of the console scripts: a run that failed, bad input (refused before
#: anything is written), a run that diverged
EXIT_FAILED, EXIT_INVALID, EXIT_DIVERGED = 1, 2, 3

__all__ = ["DivergenceError", "EnvError", "one_line", "stage_failures"]


class EnvError(RuntimeError):
    """The env returned a NaN or infinite observation or reward (``key``) in stage ``stage``."""

    def __init__(self, stage: int, name: str, key: NestedKey, cause: str) -> None:
        super().__init__(
            f"stage {stage} ({name}): the env returned a non-finite {key!r} ({cause}). Nothing "
            f"of stage {stage} was saved. Fix: the env's step/reset must return finite "
            "observations and rewards (check it with torchrl's check_env_specs and a rollout)"
        )
        self.stage, self.key = stage, key


def _path(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


@contextmanager
def stage_failures(
    stage: int,
    name: str,
    learner: Learner,
    buffer: SeedReplayBuffer,
    rows: Sequence[Any],
    seeds: Sequence[int],
) -> Iterator[None]:
    """What a non-finite loss, gradient or value in the block raises: :class:`EnvError` when the
    env's data (the replay ``buffer``'s, actions aside) is not finite, else
    :class:`DivergenceError` (naming the ``seeds`` whose ``rows`` are not finite)."""
    try:
        yield
    except (NonFiniteError, NonFiniteValueError) as err:
        env_error = partial(EnvError, stage, name)
        if isinstance(err, NonFiniteInputError):
            raise env_error(err.key, "the next stage's value of it is not finite") from err
        action, held = _path(learner.specs.action_key), buffer.held()
        for key, value in held.items(True, True) if held is not None else ():
            if action not in (_path(key), _path(key)[-1:]) and not value.isfinite().all():
                raise env_error(key, f"found in the replay buffer after: {err}") from err
        cause = err
        if len(seeds) > 1:
            finite = [all(v.isfinite().all() for v in row.state_dict().values()) for row in rows]
            broken = [s for s, ok in zip(seeds, finite, strict=True) if not ok]
            if broken:
                cause = FloatingPointError(f"{err} (seeds {broken}: their weights are not finite)")
        raise DivergenceError(stage, name, learner, cause) from err


class DivergenceError(RuntimeError):
    """A stage's training produced a NaN or infinite loss, gradient, parameter or value."""

    def __init__(self, stage: int, name: str, learner: Learner, cause: FloatingPointError) -> None:
        key = f"task.stages.{name}"
        rates = " or ".join(f"{key}.{k}" for k in learner.lr_keys)
        super().__init__(
            f"stage {stage} ({name}, {learner.algo}) diverged: {cause}. Nothing of stage "
            f"{stage} was saved. Fix: lower {rates}, or set {key}.max_grad_norm"
        )
        self.stage = stage


def one_line(err: BaseException) -> str:
    """An exception's type and the last line of its message (what ``status.json`` keeps).

    Examples:
        >>> one_line(RuntimeError("loading the map" + chr(10) + "file not found: a.txt"))
        'RuntimeError: file not found: a.txt'
    """
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[-1] if lines else ''}"
