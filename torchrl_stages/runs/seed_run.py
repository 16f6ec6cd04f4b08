"""One seed's run directory, from its checks to its ``eval.json``."""

from __future__ import annotations

import contextlib
import copy
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from hydra.errors import InstantiationException
from omegaconf import DictConfig, open_dict

from torchrl_stages.config import (
    ConfigError,
    apply_all_stages,
    expand_stage_template,
    validate_config,
)
from torchrl_stages.config.checks import validate_task
from torchrl_stages.config.env_checks import check_env_keys
from torchrl_stages.failures import DivergenceError, one_line
from torchrl_stages.learners import ALGORITHMS, Learner, learner_class
from torchrl_stages.loggers import Observer, StopRun, make_logger
from torchrl_stages.metric_names import FINAL, TASK, metric_name
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.preemption import Interrupted, stop_if_asked
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.evaluation import evaluate_run, probe_task
from torchrl_stages.runs.layout import EVAL_FILE, METRICS_FILE, STATUS_FILE, RunDirError
from torchrl_stages.runs.loading import load_stage
from torchrl_stages.runs.stage_store import StageReuse
from torchrl_stages.runs.trust import RESUMABLE_CHANGES, config_differences
from torchrl_stages.schedules import Probe, Schedule, Trained, get_schedule
from torchrl_stages.seeding import TASK_EVAL_OFFSET
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

log = logging.getLogger("torchrl_stages")


def compile_mode(cfg: DictConfig) -> str:
    """``cfg.compile``, ``auto`` resolved: ``off`` on CPU (compiling the small update costs more
    than it saves, see docs/speed.md), ``reduce-overhead`` (CUDA graphs) on a GPU."""
    mode = str(cfg.get("compile", "auto"))
    if mode != "auto":
        return mode
    return "reduce-overhead" if torch.device(cfg.device).type == "cuda" else "off"


def with_env_stages(cfg: DictConfig) -> DictConfig:
    """``cfg`` with its stages from ``task.stage_template``, as many as the env has."""
    if not cfg.task.get("stage_template"):
        return cfg
    check_env_keys(cfg)
    try:
        num_stages = StagedTask.env_num_stages(cfg.task)
    except (InstantiationException, TypeError, ValueError, RuntimeError) as err:
        raise _env_error(cfg, err) from err
    cfg = copy.deepcopy(cfg)
    with open_dict(cfg):
        cfg.task = expand_stage_template(cfg.task, num_stages)
    return cfg


def _env_error(cfg: DictConfig, err: BaseException) -> ConfigError:
    return ConfigError(
        f"task.env: cannot build the env of task '{cfg.task.name}': {err}. "
        "Fix: check the task.env.* values (or task.env._target_)."
    )


def checked_config(cfg: DictConfig) -> tuple[DictConfig, Schedule]:
    """``cfg`` with its stages filled in and validated, and its schedule."""
    cfg = with_env_stages(apply_all_stages(cfg))
    schedule = get_schedule(str(cfg.schedule.name))
    validate_config(cfg, schedule, learner_class, ALGORITHMS)
    return cfg, schedule


def build_task(cfg: DictConfig, schedule: Schedule | None = None) -> StagedTask:
    """Validates ``cfg`` (unless given the ``schedule`` it was validated with), builds its task."""
    if schedule is None:
        cfg, schedule = checked_config(cfg)
    try:
        task = StagedTask(cfg.task, device=cfg.device)
    except (InstantiationException, TypeError, ValueError, RuntimeError) as err:
        raise _env_error(cfg, err) from err
    validate_task(cfg, task, schedule, learner_class)
    return task


class SeedRun:
    """One seed's run of ``cfg`` in ``run_dir``, the :class:`~torchrl_stages.schedules.StageKeeper`
    its schedule trains into: checked before anything is written, locked until :meth:`close`
    (``task``: the one :func:`build_task` built of the same ``cfg.task``, for another seed).

    Examples:
        >>> import tempfile
        >>> from hydra import compose, initialize_config_module
        >>> from torchrl_stages.config import register_configs
        >>> from torchrl_stages.learners import ALGORITHMS
        >>> register_configs(ALGORITHMS)
        >>> with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        ...     cfg = compose("config", overrides=["experiment=smoke"])
        >>> run = SeedRun(cfg, tempfile.mkdtemp())
        >>> run.resuming, run.task.stage_names, run.finished(0)
        (False, ['s0', 's1', 's2', 's3', 's4'], None)
        >>> run.close()
    """

    def __init__(
        self,
        cfg: DictConfig,
        run_dir: str | Path,
        hydra_files: dict[str, Any] | None = None,
        observers: Sequence[Observer] = (),
        seed: int | None = None,
        task: StagedTask | None = None,
    ) -> None:
        cfg, self.schedule = checked_config(cfg)
        launch = None if seed is None else Path(run_dir).parent  # several seeds' launch
        self.cfg, self.run_dir = cfg, RunDir(run_dir, launch)
        self.hydra_files, self.observers = hydra_files, observers
        self.resume, self.overwrite = bool(cfg.get("resume")), bool(cfg.get("overwrite"))
        if self.resume and self.overwrite:
            raise ConfigError(
                "resume=true overwrite=true: pick one. Fix: resume=true continues the run, "
                "overwrite=true replaces it"
            )
        self.restarted: dict[int, list[str]] = {}  # resumed stages whose config changed
        self.reuse: StageReuse | None = None
        self.log = MetricsLog(None)
        self.seed = seed  # of a launch of several seeds: its log lines name it
        self._lock = self.run_dir.lock()
        try:
            self.resuming = self._check_run_dir()
            self.task = build_task(cfg, self.schedule) if task is None else task
            # stage_store / init_from: checked (and the stage store created) before any training
            if cfg.get("stage_store") or cfg.get("init_from"):
                self.reuse = StageReuse(cfg, self.run_dir.path)
        except BaseException:
            self._lock.release(remove=self._lock.created_dir)
            raise

    def close(self) -> None:
        if self.reuse is not None:
            self.reuse.close()
        self._lock.release()

    def _check_run_dir(self) -> bool:
        """Whether this continues a run; raises :class:`RunDirError` if it must not proceed."""
        run = self.run_dir
        if not run.holds_run():
            return False
        if self.overwrite:
            run.check_clearable()
            return False
        if not self.resume:
            raise RunDirError(
                f"{run.path} already holds a run. Fix: add resume=true to continue it, "
                "overwrite=true to replace it, or pick another hydra.run.dir"
            )
        saved = run.read_config()
        changed = config_differences(saved, self.cfg, ignore=RESUMABLE_CHANGES)
        names = list(self.cfg.task.stages)
        if names != list(saved.task.stages):  # the same keys in another order
            changed = ["task.stages (their order)", *changed]
        finished = {k for k in range(len(names)) if run.stage_file(k).is_file()}
        frozen = self.schedule.frozen_stages(finished, len(names))
        refused = []
        for key in changed:
            parts = key.split(".")
            is_stage = parts[:2] == ["task", "stages"] and len(parts) > 3
            stage = names.index(parts[2]) if is_stage and parts[2] in names else None
            if stage is None or stage in frozen or parts[2] not in saved.task.stages:
                refused.append(key)
            else:
                self.restarted.setdefault(stage, []).append(key)
        if refused:
            raise RunDirError(
                f"resume=true: the config differs from {run.config_file} in "
                f"{', '.join(refused)}; a resumed run keeps what its finished stages were "
                "trained with (stages that have not finished, and that no finished stage "
                "depends on, may change). Fix: rerun with the overrides the run was started "
                "with, or train into a new directory"
            )
        return True

    def ended(self, err: Exception) -> None:
        """Records how ``err`` ended the launch in ``status.json`` (best effort, as disks fail)."""
        outcome, reason, extra = "failed", one_line(err), {}
        if isinstance(err, Interrupted):
            outcome, reason, extra = "interrupted", str(err), {"signal": err.signal_name}
        elif isinstance(err, StopRun):  # an observer ended it (stages-tune: a pruned trial)
            outcome, reason = err.status, str(err)
        elif isinstance(err, DivergenceError):
            outcome, reason = "diverged", str(err)
        with contextlib.suppress(OSError):
            self.run_dir.update_launch(outcome)
            self.run_dir.write_status(outcome, reason, **extra)

    def start(self) -> None:
        """Prepares the directory for this launch and opens its logger."""
        cfg, run, hydra_files = self.cfg, self.run_dir, self.hydra_files
        self._lock.announce()
        if self.overwrite and run.holds_run():
            log.info("overwrite=true: removed %s", ", ".join(run.clear()) or "nothing")
        if self.resuming and not run.has_record():
            run.adopt_legacy()  # a run of a version without a record
        if hydra_files and (not self.resuming or self.restarted):
            run.write_hydra_files(hydra_files)
        for stage, keys in sorted(self.restarted.items()):
            changed = ", ".join(keys)
            log.info(f"resume=true: {changed} changed; stage {stage} had not finished and restarts")
            run.clear_checkpoints(self.schedule.checkpoint_scope(stage))
        # a resumed run missing its config.yaml was read from .hydra/config.yaml (and said so)
        if not self.resuming or self.restarted or not run.config_file.is_file():
            run.write_config(cfg)
        run.begin_launch()
        logging.getLogger("torchrl").setLevel(logging.WARNING)
        run.claim(METRICS_FILE, *(["csv"] if cfg.logger.backend == "csv" else []))
        before = run.listing()
        self.log = MetricsLog(make_logger(cfg, run.path, observers=self.observers))
        run.claim_new(before)  # a backend's own files
        self._start = time.perf_counter()

    def probe(self) -> Probe | None:
        """``eval.probe``: the whole task followed during training (``eval/task/...``)."""
        cfg, start, logger = self.cfg, self._start, self.log.logger
        if not cfg.eval.get("probe", False):
            return None

        def probe(learners: list[Learner], frames: int) -> None:
            metrics = probe_task(self.task, learners, int(cfg.seed) + TASK_EVAL_OFFSET)
            metrics["seconds"] = time.perf_counter() - start
            if logger is not None:
                for key, value in metrics.items():
                    logger.log_scalar(metric_name("eval", TASK, None, key), value, frames)

        return probe

    def _info(self, message: str, level: int = logging.INFO) -> None:
        log.log(level, message if self.seed is None else f"seed {self.seed}: {message}")

    def finished(self, stage: int, earlier: bool = True) -> tuple[Learner, StageResult] | None:
        """Stage ``stage`` as an earlier launch trained it (``earlier``), or from ``reuse``."""
        name, device = self.schedule.stage_name(self.task, stage), str(self.cfg.device)
        if self.resuming and earlier:
            loaded = load_stage(self.run_dir, self.task, stage, device, name)
            if loaded is not None:
                self._info(f"stage {stage} ({name}): finished earlier, loaded")
                return loaded[0], StageResult(**loaded[1])
        taken = None if self.reuse is None else self.reuse.take(self.task, stage, device)
        if taken is None:
            return None
        learner, result, where = taken
        self.keep("reused", {**(self.kept("reused") or {}), name: where})
        self._write(stage, name, learner, result)
        self._info(f"stage {stage} ({name}): reused from {where}")
        return learner, result

    def _write(self, stage: int, name: str, learner: Learner, result: StageResult) -> None:
        self.run_dir.save_stage(stage, name, learner, result, log=self.log.position())
        self.run_dir.clear_checkpoints(stage)
        self.run_dir.update_launch()

    def begin(self, scope: int | str) -> None:
        """A resumed run's logs rewind to where stage ``scope + 1`` ended (else the start)."""
        if not self.resuming:
            return
        later = None
        if isinstance(scope, int) and scope + 1 < self.task.num_stages:
            later = self.run_dir.read_stage(scope + 1)
        self.log.rewind({} if later is None else later["log"])  # read_stage checks it is there

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
        self._info(
            f"stage {stage} ({name}, {learner.algo}): {result.frames} frames, {result.updates} "
            f"updates, {result.seconds:.1f}s, {quality}{note}"
        )
        threshold = self.task.stage_cfg(stage).success_threshold
        if self.schedule.stage_early_stop and threshold is not None and not result.early_stopped:
            key = self.task.stage_names[stage]
            self._info(
                f"stage {stage} ({key}) did not meet its early-stop criterion within its budget "
                f"of {result.frames} frames; the run goes on with its best evaluation. Fix: raise "
                f"task.stages.{key}.frames",
                logging.WARNING,
            )

    def keep(self, key: str, value: Any) -> None:
        self.run_dir.record[key] = value

    def kept(self, key: str) -> Any:
        return self.run_dir.record.get(key)

    def clear(self, scope: int | str) -> None:
        self.run_dir.clear_checkpoints(scope)

    def finish(self, trained: Trained) -> dict[str, Any]:
        """Ends a launch: records it done, evaluates and returns ``eval.json``."""
        cfg, run = self.cfg, self.run_dir
        learners, results = trained.learners, trained.results
        stop_if_asked("the whole-task evaluation")  # a stop asked for during the last stage's save
        run.update_launch("done")
        training = {"schedule": self.schedule.name, **run.training_time()}
        training["stages"] = [asdict(r) for r in results]
        training.update(trained.extra)
        if self.reuse is not None:
            training["reused"] = reused = dict(self.kept("reused") or {})  # over every launch
            names = self.task.stage_names
            self._info(
                f"reused stages: {', '.join(n for n in names if n in reused) or 'none'}; "
                f"trained: {', '.join(n for n in names if n not in reused) or 'none'}"
            )
        before = run.listing()
        run.claim(EVAL_FILE)
        result = evaluate_run(cfg, self.task, learners, run.path, training=training)
        run.claim_new(before)  # the task's figures
        if self.resuming and self.log.logger is not None:  # an earlier final evaluation's rows
            self.log.rewind(run.read_stage(0)["log"])
        frames = sum(r.frames for r in results)  # the whole-task evaluation, after all frames
        keys = ("success_rate", "mean_return", "mean_steps")
        self.log({metric_name("eval", FINAL, None, key): result[key] for key in keys}, frames)
        (run.path / STATUS_FILE).unlink(missing_ok=True)  # an earlier launch's outcome
        return result
