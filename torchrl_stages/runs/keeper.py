"""A schedule's stages kept in a run directory: :class:`RunKeeper`, the
:class:`~torchrl_stages.schedules.StageKeeper` that each seed's
:class:`~torchrl_stages.runs.seed_run.SeedRun` passes down to the schedule it runs."""

from __future__ import annotations

import logging
from typing import Any

from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.learners import Learner
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.loading import load_stage
from torchrl_stages.runs.stage_store import StageReuse
from torchrl_stages.schedules import Schedule
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

log = logging.getLogger(__name__)

__all__ = ["RunKeeper"]


class RunKeeper:
    """Finished stages (``stage_<k>.pt``), checkpoints of the loop in progress and the logger's
    position, in the run directory ``run``.

    With ``resuming`` the stages an earlier launch finished are loaded (:meth:`finished`) and a
    loop goes on from its newest checkpoint (:meth:`begin`); without one to go on from, the
    logger's files are rewound to where the loop started, so the rows of an interrupted
    attempt are dropped. With ``reuse`` (``stage_store`` / ``init_from``) a stage is taken from
    there when it can be, and every stage trained is handed to it; :attr:`reused` says which
    stages were taken and from where.

    Examples:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.runs.directory import RunDir
        >>> from torchrl_stages.schedules import get_schedule
        >>> from torchrl_stages.task import StagedTask
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": {"a": {}, "b": {}},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2}}))
        >>> keeper = RunKeeper(RunDir(tempfile.mkdtemp()), task, get_schedule("flat"))
        >>> keeper.finished(0) is None, keeper.schedule.stage_name(task, 0)
        (True, 'flat')
    """

    def __init__(
        self,
        run: RunDir,
        task: StagedTask,
        schedule: Schedule,
        *,
        logger: Logger | None = None,
        resuming: bool = False,
        device: str = "cpu",
        checkpoint_every: int = 50_000,
        checkpoint_keep: int = 2,
        reuse: StageReuse | None = None,
    ) -> None:
        self.run, self.task, self.schedule, self.reuse = run, task, schedule, reuse
        self.log, self.resuming, self.device = MetricsLog(logger), resuming, device
        self.checkpoint_every, self.checkpoint_keep = checkpoint_every, checkpoint_keep
        # the seed of a launch of several seeds whose directory this is: its log lines say it
        self.seed: int | None = None

    def _log(self, level: int, message: str, *args: Any) -> None:
        if self.seed is not None:
            message = f"seed {self.seed}: {message}"
        log.log(level, message, *args)

    @property
    def reused(self) -> dict[str, str]:
        """``{stage name: where it was taken from}`` over every launch of the run."""
        return dict(self.run.record.get("reused", {}))

    def finished(self, stage: int) -> tuple[Learner, StageResult] | None:
        """Stage ``stage`` as trained by an earlier launch of this run (resume only), or taken
        from ``reuse`` (its stage file is then written as if this run had trained it)."""
        name = self.schedule.stage_name(self.task, stage)
        if self.resuming:
            loaded = load_stage(self.run, self.task, stage, self.device, name=name)
            if loaded is not None:
                learner, result = loaded
                self._log(logging.INFO, "stage %d (%s): finished earlier, loaded", stage, name)
                return learner, StageResult(**result)
        if self.reuse is None:
            return None
        taken = self.reuse.take(self.task, stage, self.device)
        if taken is None:
            return None
        learner, result, where = taken
        self.run.record.setdefault("reused", {})[name] = where
        self.run.save_stage(stage, name, learner, result, log=self.log.position())
        self.run.clear_checkpoints(stage)
        self.run.update_launch()
        self._log(logging.INFO, "stage %d (%s): reused from %s", stage, name, where)
        return learner, result

    def checkpoints(self, scope: int | str) -> StageCheckpoints:
        """The checkpoints of ``scope`` (a stage, or ``"joint"``) in the run directory."""
        return self.run.checkpoints(scope, self.checkpoint_every, self.checkpoint_keep)

    def begin(self, scope: int | str) -> None:
        """The loop ``scope`` starts afresh: a resumed run's logs are rewound to where it
        starts, the position stage ``scope + 1``'s file recorded (a backward stage starts
        where the stage after it ended), else the start."""
        if not self.resuming:
            return
        later = None
        if isinstance(scope, int) and scope + 1 < self.task.num_stages:
            later = self.run.read_stage(scope + 1)
        self.log.rewind({} if later is None else later.get("log", {}))

    def save(self, stage: int, learner: Learner, result: StageResult) -> None:
        """Writes ``stage_<k>.pt`` (with the log position) and drops the stage's checkpoints."""
        name = self.schedule.stage_name(self.task, stage)
        self.run.save_stage(stage, name, learner, result, log=self.log.position())
        self.run.clear_checkpoints(stage)
        self.run.update_launch()
        if self.reuse is not None:
            self.reuse.trained(self.task, stage, learner, result)
        quality = (
            f"stage success {result.success_rate:.2f}, value error {result.value_error:.3f}"
            if result.success_rate is not None
            else "not evaluated"
        )
        note = " (early stop)" if result.early_stopped else ""
        if result.restored_best:
            note = " (best evaluation restored)"
        self._log(
            logging.INFO,
            "stage %d (%s, %s): %d frames, %d updates, %.1fs, %s%s",
            stage,
            name,
            learner.algo,
            result.frames,
            result.updates,
            result.seconds,
            quality,
            note,
        )
        threshold = self.task.stage_cfg(stage).success_threshold
        if self.schedule.stage_early_stop and threshold is not None and not result.early_stopped:
            stage_name = self.task.stage_names[stage]
            self._log(
                logging.WARNING,
                "stage %d (%s) did not meet its early-stop criterion within its budget of %d "
                "frames; the run goes on with its best evaluation. Fix: raise "
                "task.stages.%s.frames",
                stage,
                stage_name,
                result.frames,
                stage_name,
            )

    def keep(self, key: str, value: Any) -> None:
        """Keeps ``value`` in the run's record (written with the next stage or launch)."""
        self.run.record[key] = value

    def kept(self, key: str) -> Any:
        return self.run.record.get(key)

    def clear(self, scope: int | str) -> None:
        self.run.clear_checkpoints(scope)

    def close(self) -> None:
        """Releases what ``reuse`` still holds (the lock of a stage that did not finish)."""
        if self.reuse is not None:
            self.reuse.close()
