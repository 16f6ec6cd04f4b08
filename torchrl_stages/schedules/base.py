"""What a schedule is: how a task's stages are trained, one module each, known by name.

A :class:`Schedule` trains a task's learners (:meth:`Schedule.train`) and says what its runs
look like on disk and on resume: which stages a finished one freezes, which checkpoints a
restarted stage drops, which stage file holds each stage's learner. It keeps its stages in a
:class:`StageKeeper` that the caller passes down (a run directory,
:class:`~torchrl_stages.runs.keeper.RunKeeper`, or nothing): the schedule never calls back into
the code that runs it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from omegaconf import DictConfig

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import ConfigError
from torchrl_stages.learners import Learner
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

__all__ = [
    "SCHEDULES",
    "begin_loop",
    "finished_for_every_seed",
    "Probe",
    "Schedule",
    "StageKeeper",
    "Trained",
    "get_schedule",
    "register_schedule",
]

#: ``probe(learners, frames)``: follows the whole task during training (see ``eval.probe``);
#: called at every evaluation of the stage that holds the whole-task starts, with the
#: learners as they are and the frames collected so far over all stages
Probe = Callable[[list[Learner], int], None]


class StageKeeper(Protocol):
    """Where a schedule keeps its stages (a run directory:
    :class:`~torchrl_stages.runs.keeper.RunKeeper`): finished ones, checkpoints of the one in
    progress, and what else a schedule needs to resume (``keep`` / ``kept``)."""

    def finished(self, stage: int) -> tuple[Learner, StageResult] | None:
        """The stage if it was already trained (a resumed run), else ``None``."""

    def begin(self, scope: int | str) -> None:
        """A loop (``scope``: a stage's index, or a name such as ``"joint"`` for a loop over
        every stage) starts afresh: the logs are rewound to where it starts (a resumed run
        drops the rows of an attempt that was interrupted)."""

    def save(self, stage: int, learner: Learner, result: StageResult) -> None:
        """Keeps a stage that just finished."""

    def keep(self, key: str, value: Any) -> None:
        """Keeps ``value`` (JSON) for a later launch of the run."""

    def kept(self, key: str) -> Any:
        """What :meth:`keep` kept under ``key`` (``None``: nothing)."""

    def clear(self, scope: int | str) -> None:
        """Drops the checkpoints of ``scope``."""


@dataclass
class Trained:
    """What a schedule returns: one learner and one result per stage (a flat learner: the same
    learner in every stage, one result), and what else ``eval.json``'s ``training`` records."""

    learners: list[Learner]
    results: list[StageResult]
    extra: dict[str, Any] = field(default_factory=dict)


class Schedule:
    """How a task's stages are trained. A schedule is one module: a subclass with a ``name``,
    registered with :func:`register_schedule`, selected by ``schedule=<name>``.

    Examples:
        >>> sorted(SCHEDULES)
        ['backward', 'flat', 'joint']
        >>> get_schedule("backward").frozen_stages({3, 4}, 5)
        {3, 4}
    """

    name: ClassVar[str]
    #: whether a stage is trained until its own early stop (a stage that did not meet it is
    #: warned about)
    stage_early_stop: ClassVar[bool] = True
    #: whether a stage is determined by its own config and the stages after it alone, so that
    #: a finished one can be reused by another run (``stage_store``, ``init_from``)
    reuses_stages: ClassVar[bool] = False
    #: whether :meth:`train` trains several seeds in one process (``seeds=[...]``)
    stacks_seeds: ClassVar[bool] = False

    def train(self, task: StagedTask, seeds: Sequence[int] = (0,), **kwargs: Any) -> list[Trained]:
        """Trains (what is left of) ``task``'s stages for every seed of ``seeds`` at once
        (several: their networks stacked, see :mod:`torchrl_stages.stage`); one
        :class:`Trained` per seed. ``kwargs``: ``keepers`` and ``logs`` (one per seed: where
        each seed's stages are kept and its metrics logged), ``checkpoints`` (a checkpoint
        scope (:meth:`checkpoint_scope`) -> its
        :class:`~torchrl_stages.checkpoint.StageCheckpoints`, one state for all the seeds),
        ``progress``, ``probe`` (one seed) and ``compile``."""
        raise NotImplementedError

    def frozen_stages(self, finished: set[int], num_stages: int) -> set[int]:
        """The stages whose config a resumed run may not change, given the ``finished`` ones:
        those a finished stage depends on (by default every stage once one has finished)."""
        return set(range(num_stages)) if finished else set()

    def checkpoint_scope(self, stage: int) -> int | str:
        """The checkpoints that hold stage ``stage`` in progress."""
        return stage

    def stored_stage(self, stage: int) -> int:
        """The stage file that holds stage ``stage``'s learner."""
        return stage

    def stage_name(self, task: StagedTask, stage: int) -> str:
        """The name stage ``stage``'s file is written with."""
        return task.stage_names[stage]

    def validate(self, cfg: DictConfig) -> None:
        """Checks the config before the env is built (:class:`ConfigError`)."""

    def validate_task(self, cfg: DictConfig, task: StagedTask) -> None:
        """Checks the built task (:class:`ConfigError`)."""


def finished_for_every_seed(
    keepers: Sequence[StageKeeper | None], seeds: Sequence[int], stage: int, resume: str
) -> list[tuple[Learner, StageResult]] | None:
    """Each seed's finished ``stage`` (``keeper.finished(stage)``) when every seed's keeper has
    it, ``None`` when none has; a ``RuntimeError`` naming the seeds and the fix (``resume``: the
    command that resumes one seed's run directory) when only some have."""
    done = [keeper.finished(stage) if keeper is not None else None for keeper in keepers]
    if all(d is None for d in done):
        return None
    missing = [s for s, d in zip(seeds, done, strict=True) if d is None]
    if missing:
        raise RuntimeError(
            f"stage {stage}: finished for some seeds but not for seeds {missing}; Fix: resume "
            f"those seeds' run directories one by one ({resume})"
        )
    return done


def begin_loop(
    keepers: Sequence[StageKeeper | None],
    checkpoints: Callable[[int | str], StageCheckpoints] | None,
    scope: int | str,
) -> StageCheckpoints | None:
    """The checkpoints of the loop ``scope`` (none without ``checkpoints``); without one to go
    on from, each seed's keeper starts the loop afresh (:meth:`StageKeeper.begin`)."""
    scoped = checkpoints(scope) if checkpoints is not None else None
    if scoped is None or scoped.latest() is None:
        for keeper in keepers:
            if keeper is not None:
                keeper.begin(scope)
    return scoped


#: registered schedules by name
SCHEDULES: dict[str, type[Schedule]] = {}


def register_schedule(cls: type[Schedule]) -> type[Schedule]:
    """Class decorator: makes ``cls`` the schedule ``schedule=<cls.name>`` selects."""
    SCHEDULES[cls.name] = cls
    return cls


def get_schedule(name: str) -> Schedule:
    """The schedule registered as ``name``; :class:`ConfigError` names the known ones."""
    if name not in SCHEDULES:
        raise ConfigError(
            f"schedule.name={name!r}: unknown schedule (known: {', '.join(sorted(SCHEDULES))}). "
            f"Fix: select one with schedule={'|'.join(sorted(SCHEDULES))}"
        )
    return SCHEDULES[name]()
