"""One training run, start to end: the library API behind ``stages-train``.

:class:`Experiment` validates a config, takes and checks its run directory, builds the task,
trains every stage with periodic checkpoints, resumes an interrupted run, and evaluates. The
CLI, ``stages-eval``, the benchmark scripts and Python users all go through it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from hydra.errors import InstantiationException
from omegaconf import DictConfig

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.joint import JointTrainer
from torchrl_stages.learners import Learner
from torchrl_stages.loggers import make_logger
from torchrl_stages.preemption import Interrupted, check, handle_signals
from torchrl_stages.reports import EVAL_SEED_OFFSET, evaluate_run, probe_task
from torchrl_stages.rundir import (
    METRICS_FILE,
    STATUS_FILE,
    RunDir,
    RunDirError,
    config_differences,
    load_stage,
)
from torchrl_stages.schedule import train_backward, train_flat
from torchrl_stages.stage import DivergenceError, StageResult
from torchrl_stages.task import StagedTask
from torchrl_stages.threads import hold_threads
from torchrl_stages.validate import ConfigError, validate_config, validate_task

log = logging.getLogger("torchrl_stages")

#: keys a resumed run may change: they do not touch what was trained
RESUMABLE_CHANGES = (
    "resume",
    "overwrite",
    "progress",
    "eval",
    "objective",
    "checkpoint_every",
    "checkpoint_keep",
)


def one_line(err: BaseException) -> str:
    """An exception as one line: its type and the last line of its message (what
    ``status.json`` keeps of a failure).

    Examples:
        >>> one_line(RuntimeError("loading the map" + chr(10) + "file not found: a.txt"))
        'RuntimeError: file not found: a.txt'
    """
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[-1] if lines else ''}"


def compile_mode(cfg: DictConfig) -> str:
    """``cfg.compile`` with ``auto`` resolved for the run's device: ``off`` on CPU (compiling
    the small update costs more than it saves, see the README's speed table),
    ``reduce-overhead`` (CUDA graphs) on a GPU."""
    mode = str(cfg.get("compile", "auto"))
    if mode != "auto":
        return mode
    return "reduce-overhead" if torch.device(cfg.device).type == "cuda" else "off"


def build_task(cfg: DictConfig) -> StagedTask:
    """Validates ``cfg`` and builds its task; raises :class:`ConfigError` before any training."""
    validate_config(cfg)
    try:
        task = StagedTask(cfg.task, device=cfg.device)
    except (InstantiationException, TypeError, ValueError, RuntimeError) as err:
        raise ConfigError(
            f"task.env: cannot build the env of task '{cfg.task.name}': {err}. "
            "Fix: check the task.env.* values (or task.env._target_)."
        ) from err
    validate_task(cfg, task)
    return task


def frozen_stages(schedule: str, finished: set[int], num_stages: int) -> set[int]:
    """The stages whose config a resumed run may not change: those a finished stage depends
    on. In the backward schedule stage k is trained from its own config and the values of the
    stages after it; the joint and flat schedules train every stage at once.

    Examples:
        >>> sorted(frozen_stages("backward", {3, 4}, 5)), sorted(frozen_stages("joint", set(), 5))
        ([3, 4], [])
    """
    if not finished:
        return set()
    if schedule == "backward":
        return set(range(min(finished), num_stages))
    return set(range(num_stages))


class Experiment:
    """Trains and evaluates one run of ``cfg`` in ``run_dir``.

    Everything is checked when the experiment is built, before anything is written: the config
    (:class:`~torchrl_stages.validate.ConfigError`) and the run directory
    (:class:`~torchrl_stages.rundir.RunDirError`), which it locks until the run ends (one
    process per directory). A directory that already holds a run is refused unless ``resume``
    (continue it: finished stages are loaded, the stage in progress goes on from its last
    checkpoint; keys of stages that no finished stage depends on may change, and those stages
    restart) or ``overwrite`` (replace it: exactly the files its record lists are deleted).
    Both default to ``cfg.resume`` / ``cfg.overwrite``. With ``resume`` and no run in the
    directory, a new run starts (the same command can be relaunched after any interruption).
    ``hydra_files`` (``{name: config}``) are written to ``.hydra/`` when the run starts or its
    config changes (what ``stages-train`` records of Hydra).

    While it runs, SIGTERM, SIGINT and SIGUSR1 stop it at the next batch with a checkpoint
    (:mod:`torchrl_stages.preemption`), and the torch thread count is held at ``cfg.threads``.

    Examples:
        >>> from hydra import compose, initialize_config_module
        >>> from torchrl_stages.store import register_configs
        >>> register_configs()
        >>> with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        ...     cfg = compose("config", overrides=["experiment=smoke"])  # doctest: +SKIP
        >>> result = Experiment(cfg, "runs/grid").run()  # doctest: +SKIP
        >>> result["success_rate"]  # doctest: +SKIP
        1.0
    """

    def __init__(
        self,
        cfg: DictConfig,
        run_dir: str | Path,
        *,
        resume: bool | None = None,
        overwrite: bool | None = None,
        hydra_files: dict[str, Any] | None = None,
    ) -> None:
        self.cfg = cfg
        self.hydra_files = dict(hydra_files or {})
        self.run_dir = RunDir(run_dir)
        self.resume = bool(cfg.get("resume", False) if resume is None else resume)
        self.overwrite = bool(cfg.get("overwrite", False) if overwrite is None else overwrite)
        validate_config(cfg)
        if self.resume and self.overwrite:
            raise ConfigError(
                "resume=true overwrite=true: pick one. Fix: resume=true continues the run, "
                "overwrite=true replaces it"
            )
        self.restarted: dict[int, list[str]] = {}  # resumed stages whose config changed
        self._lock = self.run_dir.lock()
        try:
            self.resuming = self._check_run_dir()
            self.task = build_task(cfg)
        except BaseException:
            self._lock.release(remove=self._lock.created_dir)
            raise
        self.logger = None

    def close(self) -> None:
        """Releases the run directory (:meth:`run` does it when it ends)."""
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
        frozen = frozen_stages(self.cfg.schedule.name, finished, len(names))
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

    # ------------------------------------------------------------------ the run
    def run(self) -> dict[str, Any]:
        """Trains every stage (or what is left of them) and evaluates; returns ``eval.json``.

        How it ended is in the run's record (its launches) and, when it did not finish, in
        ``status.json``: ``interrupted`` (:class:`~torchrl_stages.preemption.Interrupted`),
        ``diverged`` (:class:`~torchrl_stages.stage.DivergenceError`) or ``failed``."""
        try:
            with handle_signals(), hold_threads(int(self.cfg.threads)):
                try:
                    self._prepare()
                    return self._run()
                except Interrupted as err:  # recorded before a launcher's handler runs
                    self._ended("interrupted", str(err), signal=err.signal_name)
                    raise
        except Interrupted:
            raise
        except DivergenceError as err:
            self._ended("diverged", str(err))
            raise
        except Exception as err:
            self._ended("failed", one_line(err))
            raise
        finally:
            self.close()

    def _ended(self, outcome: str, reason: str, **extra: Any) -> None:
        """Records how a launch that did not finish ended (best effort: the disk may be the
        cause)."""
        try:
            self.run_dir.update_launch(outcome)
            self.run_dir.write_status(outcome, reason, **extra)
        except OSError:
            pass

    def _prepare(self) -> None:
        """Writes what a run starts with: a fresh record and config, or the changes a resumed
        run may make."""
        cfg, run = self.cfg, self.run_dir
        self._lock.announce()
        if self.overwrite and run.holds_run():
            removed = run.clear()
            log.info("overwrite=true: removed %s", ", ".join(removed) or "nothing")
        if self.resuming and not run.has_record():
            run.adopt_legacy()  # a run of a version without a record
        if self.hydra_files and (not self.resuming or self.restarted):
            run.write_hydra_files(self.hydra_files)
        if not self.resuming:
            run.write_config(cfg)
        elif not run.config_file.is_file():  # checked against .hydra/config.yaml: the same
            log.warning("%s was missing: restored from .hydra/config.yaml", run.config_file)
            run.write_config(cfg)
        if self.restarted:
            schedule = cfg.schedule.name
            for stage, keys in sorted(self.restarted.items()):
                log.info(
                    "resume=true: %s changed; stage %d had not finished and restarts",
                    ", ".join(keys),
                    stage,
                )
                run.clear_checkpoints("joint" if schedule == "joint" else stage)
            if schedule == "flat":
                run.clear_checkpoints(0)
            run.write_config(cfg)
        run.begin_launch()

    def _run(self) -> dict[str, Any]:
        cfg, run = self.cfg, self.run_dir
        logging.getLogger("torchrl").setLevel(logging.WARNING)
        run.claim(METRICS_FILE, *(["csv"] if cfg.logger.backend == "csv" else []))
        before = run.listing()
        self.logger = make_logger(cfg, run.path)
        run.claim_new(before)  # a backend's own files
        start, schedule, phases = time.perf_counter(), cfg.schedule.name, None
        kwargs = {
            "seed": int(cfg.seed),
            "logger": self.logger,
            "progress": cfg.progress,
            "compile": compile_mode(cfg),
        }
        if kwargs["compile"] != "off":
            # compiled code starts fresh in every run: the jobs of a sweep run one after another
            # in one process, and their learners' recompiles would add up to Dynamo's limit
            torch._dynamo.reset()
        if cfg.eval.get("probe", False):

            def probe(learners: list[Learner], frames: int) -> None:
                seed = int(cfg.seed) + EVAL_SEED_OFFSET
                metrics = {**probe_task(self.task, learners, seed)}
                metrics["seconds"] = time.perf_counter() - start
                if self.logger is not None:
                    for key, value in metrics.items():
                        self.logger.log_scalar(f"eval/task/{key}", value, step=frames)

            kwargs["probe"] = probe
        if schedule == "joint":
            learners, results, phases = self._train_joint(**kwargs)
        elif schedule == "flat":
            learners, results = train_flat(self.task, store=self, **kwargs)
        else:
            learners, results = train_backward(self.task, store=self, **kwargs)
        check("the whole-task evaluation")  # a stop asked for during the last stage's save
        run.update_launch("done")
        training = {"schedule": schedule, **run.training_time()}
        training["stages"] = [asdict(r) for r in results]
        if phases is not None:
            training["phases"] = phases
        before = run.listing()
        run.claim("eval.json")
        result = evaluate_run(cfg, self.task, learners, run.path, training=training)
        run.claim_new(before)  # the task's figures
        if self.logger is not None:  # the run's whole-task evaluation, after all its frames
            rewind = getattr(self.logger, "rewind", None)
            if self.resuming and rewind is not None:  # rows of an earlier final evaluation
                rewind(run.read_stage(0)["log"])
            frames = sum(r.frames for r in results)
            for key in ("success_rate", "mean_return", "mean_steps"):
                self.logger.log_scalar(f"eval/final/{key}", result[key], step=frames)
        (run.path / STATUS_FILE).unlink(missing_ok=True)  # an earlier launch's outcome
        return result

    def _train_joint(self, **kwargs: Any) -> tuple[list[Learner], list[StageResult], list]:
        """The joint schedule: resumable as a whole, its stages written once it ends."""
        task, run = self.task, self.run_dir
        if self.resuming and all(run.stage_file(k).is_file() for k in range(task.num_stages)):
            stages = [self.finished(k) for k in range(task.num_stages)]
            phases = list(run.record.get("phases", []))
            return [s[0] for s in stages], [s[1] for s in stages], phases
        checkpoints = run.checkpoints(
            "joint", int(self.cfg.checkpoint_every), int(self.cfg.checkpoint_keep)
        )
        rewind = getattr(self.logger, "rewind", None)
        if self.resuming and checkpoints.latest() is None and rewind is not None:
            rewind({})
        learners, results, phases = JointTrainer(task, checkpoints=checkpoints, **kwargs).train()
        for phase in phases:
            start = (
                "the task's own starts"
                if phase["start_stage"] is None
                else (f"stage {phase['start_stage']} starts")
            )
            log.info(
                "joint phase from %s: %d frames, whole-task success %.2f, value error %.3f%s",
                start,
                phase["frames"],
                phase["success_rate"] if phase["success_rate"] is not None else float("nan"),
                phase["value_error"] if phase["value_error"] is not None else float("nan"),
                " (early stop)" if phase["early_stopped"] else " (budget used, best restored)",
            )
        run.record["phases"] = phases  # kept for a resumed launch's eval.json
        for k in range(task.num_stages):
            self.save(k, learners[k], results[k])
        run.clear_checkpoints("joint")
        return learners, results, phases

    # ------------------------------------------------------------------ stage store
    def finished(self, stage: int) -> tuple[Learner, StageResult] | None:
        """Stage ``stage`` as trained by an earlier launch of this run (resume only)."""
        if not self.resuming:
            return None
        loaded = load_stage(self.run_dir, self.task, stage, self.cfg.device)
        if loaded is None:
            return None
        learner, result = loaded
        log.info("stage %d (%s): finished earlier, loaded", stage, self.task.stage_names[stage])
        return learner, StageResult(**result)

    def begin(self, stage: int) -> StageCheckpoints:
        """Stage ``stage``'s checkpoints; without one to resume from, the logs are rewound to
        where the stage started (rows of an interrupted attempt are dropped)."""
        cfg = self.cfg
        checkpoints = self.run_dir.checkpoints(
            stage, int(cfg.checkpoint_every), int(cfg.checkpoint_keep)
        )
        if self.resuming and checkpoints.latest() is None:
            later = self.run_dir.read_stage(stage + 1) if stage + 1 < self.task.num_stages else None
            rewind = getattr(self.logger, "rewind", None)
            if rewind is not None:
                rewind({} if later is None else later.get("log", {}))
        elif self.resuming:
            log.info("stage %d: resuming from %s", stage, checkpoints.latest())
        return checkpoints

    def save(self, stage: int, learner: Learner, result: StageResult) -> None:
        """Writes ``stage_<k>.pt`` (with the log position) and drops the stage's checkpoints."""
        position = getattr(self.logger, "position", None)
        name = "flat" if self.cfg.schedule.name == "flat" else self.task.stage_names[stage]
        self.run_dir.save_stage(
            stage,
            name,
            learner,
            result,
            log=position() if position is not None else {},
        )
        self.run_dir.clear_checkpoints(stage)
        self.run_dir.update_launch()
        quality = (
            f"stage success {result.success_rate:.2f}, value error {result.value_error:.3f}"
            if result.success_rate is not None
            else "not evaluated"
        )
        note = " (early stop)" if result.early_stopped else ""
        if result.restored_best:
            note = " (best evaluation restored)"
        log.info(
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
        if self.cfg.schedule.name != "joint" and threshold is not None and not result.early_stopped:
            log.warning(
                "stage %d (%s) did not meet its early-stop criterion within its budget of %d "
                "frames; the run goes on with its best evaluation. Fix: raise "
                "task.stages.%s.frames",
                stage,
                self.task.stage_names[stage],
                result.frames,
                self.task.stage_names[stage],
            )


__all__ = ["Experiment", "RunDirError", "build_task"]
