"""What a schedule is (:class:`Schedule`), the seeds it trains together (:class:`SeedGroup`)
and what it returns (:class:`Trained`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from omegaconf import DictConfig

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import ConfigError
from torchrl_stages.learners import Learner
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.stage import SeedResults, StageResult
from torchrl_stages.task import StagedTask

#: ``probe(learners, frames)`` (``eval.probe``): the whole task followed at the evaluations of
#: the stage that holds its starts, with the frames so far over all stages
Probe = Callable[[list[Learner], int], None]

log = logging.getLogger(__name__)


class StageKeeper(Protocol):
    """Where a schedule keeps a seed's stages (:class:`~torchrl_stages.runs.seed_run.SeedRun`)."""

    def finished(self, stage: int, earlier: bool = True) -> tuple[Learner, StageResult] | None:
        """The stage if a previous launch trained it (``earlier``: else only one that a shared
        store has under its identity and the later stages'), else ``None``."""

    def begin(self, scope: int | str) -> None:
        """Loop ``scope`` starts afresh: the logs are rewound to where it starts."""

    def save(self, stage: int, learner: Learner, result: StageResult) -> None: ...

    def keep(self, key: str, value: Any) -> None:
        """Keeps ``value`` (JSON) for a later launch of the run."""

    def kept(self, key: str) -> Any: ...

    def clear(self, scope: int | str) -> None:
        """Drops the checkpoints of ``scope``."""


@dataclass
class Trained:
    """What a schedule returns for a seed: one learner and one result per stage, and what else
    ``eval.json``'s ``training`` records."""

    learners: list[Learner]
    results: list[StageResult]
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def per_seed(cls, stages: Sequence[SeedResults]) -> list[Trained]:
        """One per seed, from each stage's ``(learner, result)`` of every seed."""
        return [cls(*map(list, zip(*seed, strict=True))) for seed in zip(*stages, strict=True)]


@dataclass
class SeedGroup:
    """The seeds one :meth:`Schedule.train` call trains together, each one's keeper and log, the
    checkpoints of a loop scope (one state for all the seeds), and how the loops run."""

    seeds: list[int]
    keepers: Sequence[StageKeeper | None] | None = None
    logs: Sequence[MetricsLog] | None = None
    checkpoints: Callable[[int | str], StageCheckpoints] | None = None
    progress: bool = False
    probe: Probe | None = None
    compile: str = "off"
    trained: bool = field(default=False, init=False)  # whether a stage trained in this launch

    def __post_init__(self) -> None:
        self.keepers = list(self.keepers or [None] * len(self.seeds))

    def finished(self, stage: int, earlier: bool = True) -> SeedResults | None:
        """Each seed's finished ``stage`` (:meth:`StageKeeper.finished`) when every keeper has
        it, else ``None`` (a stage finished for some seeds only trains again for all)."""
        done = [k.finished(stage, earlier) if k is not None else None for k in self.keepers]
        missing = [s for s, d in zip(self.seeds, done, strict=True) if d is None]
        if missing and len(missing) < len(done):
            log.warning(
                "stage %d is finished for some seeds but not for seeds %s: it trains again for "
                "every seed, and so do the stages trained after it",
                stage,
                missing,
            )
        return None if missing else done

    def begin(self, scope: int | str) -> StageCheckpoints | None:
        """The checkpoints of loop ``scope`` (none to go on from: each keeper starts it afresh)."""
        scoped = self.checkpoints(scope) if self.checkpoints is not None else None
        if scoped is None or scoped.latest() is None:
            for keeper in self.keepers:
                if keeper is not None:
                    keeper.begin(scope)
        return scoped

    def stage(self, stage: int, train: Callable[..., SeedResults]) -> SeedResults:
        """Each seed's ``stage``: finished earlier, else ``train(checkpoints=...)``, kept (its
        checkpoints dropped). Once a stage trains, the run's own files and checkpoints of the
        stages after it are not used: they were trained against the stages before as they were.
        """
        done = self.finished(stage, earlier=not self.trained)
        if done is None:
            kept = any(keeper is not None for keeper in self.keepers)  # else none of them is
            if self.trained and kept and self.checkpoints is not None:
                self.checkpoints(stage).clear()
            self.trained = True
            checkpoints = self.begin(stage)
            done = train(checkpoints=checkpoints)
            for keeper, (learner, result) in zip(self.keepers, done, strict=True):
                if keeper is not None:
                    keeper.save(stage, learner, result)
            if checkpoints is not None:
                checkpoints.clear()
        return done


class Schedule:
    """How a task's stages are trained: a subclass with a ``name``, registered with
    :func:`register_schedule`, selected by ``schedule=<name>``.

    Examples:
        >>> sorted(SCHEDULES)
        ['backward', 'flat', 'joint']
        >>> get_schedule("backward").frozen_stages({3, 4}, 5)
        {3, 4}
    """

    name: ClassVar[str]
    #: whether a stage trains until its own early stop (one that did not meet it is warned about)
    stage_early_stop: ClassVar[bool] = True
    #: whether a finished stage can be reused by another run (``stage_store``, ``init_from``)
    reuses_stages: ClassVar[bool] = False
    #: whether :meth:`train` trains several seeds in one process (``seeds=[...]``)
    stacks_seeds: ClassVar[bool] = False

    def train(self, task: StagedTask, seeds: Sequence[int] = (0,), **kwargs: Any) -> list[Trained]:
        """Trains what is left of ``task`` for every seed (``kwargs``: :class:`SeedGroup`'s)."""
        return self.run(task, SeedGroup(list(seeds), **kwargs))

    def run(self, task: StagedTask, group: SeedGroup) -> list[Trained]:
        """What each schedule implements: one :class:`Trained` per seed of ``group``."""
        raise NotImplementedError

    def frozen_stages(self, finished: set[int], num_stages: int) -> set[int]:
        """The stages whose config a resumed run may not change, given the ``finished`` ones."""
        return set(range(num_stages)) if finished else set()

    def checkpoint_scope(self, stage: int) -> int | str:
        """The checkpoints that hold stage ``stage`` in progress."""
        return stage

    def stored_stage(self, stage: int) -> int:
        """The stage file that holds stage ``stage``'s learner."""
        return stage

    def stage_name(self, task: StagedTask, stage: int) -> str:
        return task.stage_names[stage]

    def validate(self, cfg: DictConfig) -> None:
        """Checks the config before the env is built (:class:`ConfigError`)."""

    def validate_task(self, cfg: DictConfig, task: StagedTask) -> None:
        """Checks the built task (:class:`ConfigError`)."""


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
