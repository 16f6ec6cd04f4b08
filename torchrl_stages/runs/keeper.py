"""The :class:`~torchrl_stages.schedules.StageKeeper` that keeps a schedule's stages in a run
directory."""

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
    """Finished stages, checkpoints of the loop in progress and the logger's position in
    ``run``. With ``resuming``, finished stages are loaded and a loop restarted afresh rewinds
    the logger's files; with ``reuse``, stages are taken from there when they can be.

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
        self.seed: int | None = None

    def _log(self, level: int, message: str) -> None:
        log.log(level, message if self.seed is None else f"seed {self.seed}: {message}")

    @property
    def reused(self) -> dict[str, str]:
        """``{stage name: where it was taken from}`` over every launch."""
        return dict(self.run.record.get("reused", {}))

    def finished(self, stage: int) -> tuple[Learner, StageResult] | None:
        """Stage ``stage`` as an earlier launch trained it, or taken from ``reuse``."""
        name = self.schedule.stage_name(self.task, stage)
        if self.resuming:
            loaded = load_stage(self.run, self.task, stage, self.device, name=name)
            if loaded is not None:
                self._log(logging.INFO, f"stage {stage} ({name}): finished earlier, loaded")
                return loaded[0], StageResult(**loaded[1])
        taken = None if self.reuse is None else self.reuse.take(self.task, stage, self.device)
        if taken is None:
            return None
        learner, result, where = taken
        self.run.record.setdefault("reused", {})[name] = where
        self._write(stage, name, learner, result)
        self._log(logging.INFO, f"stage {stage} ({name}): reused from {where}")
        return learner, result

    def _write(self, stage: int, name: str, learner: Learner, result: StageResult) -> None:
        self.run.save_stage(stage, name, learner, result, log=self.log.position())
        self.run.clear_checkpoints(stage)
        self.run.update_launch()

    def checkpoints(self, scope: int | str) -> StageCheckpoints:
        return self.run.checkpoints(scope, self.checkpoint_every, self.checkpoint_keep)

    def begin(self, scope: int | str) -> None:
        """The loop ``scope`` starts afresh: a resumed run's logs are rewound to where stage
        ``scope + 1`` ended (a backward stage starts there), else to the start."""
        if not self.resuming:
            return
        later = None
        if isinstance(scope, int) and scope + 1 < self.task.num_stages:
            later = self.run.read_stage(scope + 1)
        self.log.rewind({} if later is None else later.get("log", {}))

    def save(self, stage: int, learner: Learner, result: StageResult) -> None:
        name = self.schedule.stage_name(self.task, stage)
        self._write(stage, name, learner, result)
        if self.reuse is not None:
            self.reuse.trained(self.task, stage, learner, result)
        quality = "not evaluated"
        if result.success_rate is not None:
            quality = (
                f"stage success {result.success_rate:.2f}, value error {result.value_error:.3f}"
            )
        note = " (early stop)" if result.early_stopped else ""
        if result.restored_best:
            note = " (best evaluation restored)"
        self._log(
            logging.INFO,
            f"stage {stage} ({name}, {learner.algo}): {result.frames} frames, {result.updates} "
            f"updates, {result.seconds:.1f}s, {quality}{note}",
        )
        threshold = self.task.stage_cfg(stage).success_threshold
        if self.schedule.stage_early_stop and threshold is not None and not result.early_stopped:
            key = self.task.stage_names[stage]
            self._log(
                logging.WARNING,
                f"stage {stage} ({key}) did not meet its early-stop criterion within its budget "
                f"of {result.frames} frames; the run goes on with its best evaluation. Fix: raise "
                f"task.stages.{key}.frames",
            )

    def keep(self, key: str, value: Any) -> None:
        """Keeps ``value`` in the run's record (written with the next stage or launch)."""
        self.run.record[key] = value

    def kept(self, key: str) -> Any:
        return self.run.record.get(key)

    def clear(self, scope: int | str) -> None:
        self.run.clear_checkpoints(scope)

    def close(self) -> None:
        if self.reuse is not None:
            self.reuse.close()
