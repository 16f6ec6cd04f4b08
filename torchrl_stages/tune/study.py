"""An Optuna study whose trial ``n`` is a ``stages-train`` run in ``<study dir>/<n>/``, pruned on
its stage evaluations; the study directory gets the sweep summary and ``best.yaml``."""

from __future__ import annotations

import traceback
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.checkpoint import CheckpointDamagedError
from torchrl_stages.config import ConfigError, apply_all_stages, check, stage_keys_set
from torchrl_stages.config.registration import hydra_message
from torchrl_stages.failures import EXIT_FAILED, DivergenceError, EnvError, one_line
from torchrl_stages.integrity import DamagedFileError
from torchrl_stages.loggers import StopRun
from torchrl_stages.metric_names import is_loop_evaluation
from torchrl_stages.preemption import Interrupted
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.sweeps import summarize_or_say
from torchrl_stages.tune.space import Compose, ParamSpec, checked_search, hydra_value

BEST_FILE = "best.yaml"
# a run's failures that say what went wrong: its trial fails, the study goes on
RUN_ERRORS = (DivergenceError, EnvError, RunDirError, CheckpointDamagedError, DamagedFileError)


class TrialFailed(RuntimeError):
    """A trial whose run did not finish: failed in the study, which goes on."""


class StudyError(RuntimeError):
    """The study cannot go on (a trial's directory holds another run, a disk error)."""


@dataclass
class StudyContext:
    """Where a study runs; ``hydra_cfg`` is written to each trial's ``.hydra/hydra.yaml``.

    Examples:
        >>> StudyContext(Path("tune/grid"), Path("."), ["tune.n_trials=4"], print).study_dir
        PosixPath('tune/grid')
    """

    study_dir: Path
    cwd: Path
    overrides: list[str]
    compose: Compose
    hydra_cfg: DictConfig | None = None


class TrialPruning:
    """A run's :data:`~torchrl_stages.loggers.Observer` that reports each loop evaluation's
    success rate (the failure rate when minimizing) to an Optuna ``trial``, step: the
    evaluation's index in the run, and raises ``StopRun("pruned")`` when the trial should stop.

    Examples:
        >>> from types import SimpleNamespace
        >>> trial = SimpleNamespace(report=lambda value, step: None, should_prune=lambda: True)
        >>> TrialPruning(trial)({"eval/stage_4/success_rate": 0.25}, 1024)
        Traceback (most recent call last):
        ...
        torchrl_stages.loggers.StopRun: pruned at stage evaluation 0 (...=0.25 at 1024 frames ...)
    """

    def __init__(self, trial: Any, direction: str = "maximize") -> None:
        self.trial = trial
        self.minimize = direction == "minimize"
        self.evaluations = 0

    def __call__(self, metrics: dict[str, float], step: int) -> None:
        for name in filter(is_loop_evaluation, metrics):
            index, self.evaluations = self.evaluations, self.evaluations + 1
            success = float(metrics[name])
            self.trial.report(1.0 - success if self.minimize else success, index)
            if self.trial.should_prune():
                where = f"{name}={success:g} at {step} frames of the stage"
                raise StopRun("pruned", f"pruned at stage evaluation {index} ({where})")


def make_pruner(tune: DictConfig, direction: str) -> Any:
    """The Optuna pruner ``tune.pruner`` names, over what :class:`TrialPruning` reports."""
    from optuna import pruners

    warmup, startup = int(tune.warmup_steps), int(tune.startup_trials)
    if tune.pruner == "median":
        return pruners.MedianPruner(n_startup_trials=startup, n_warmup_steps=warmup)
    if tune.pruner == "threshold":
        below = float(tune.prune_below)  # minimize: failure rates above 1 - below are pruned
        limit = {"upper": 1.0 - below} if direction == "minimize" else {"lower": below}
        return pruners.ThresholdPruner(**limit, n_warmup_steps=warmup)
    return pruners.NopPruner()


def _run_trial(
    trial: Any, cfg: DictConfig, space: list[ParamSpec], base: list[str], context: StudyContext
) -> float:
    import optuna

    overrides = [*base, *(spec.override(spec.suggest(trial)) for spec in space)]
    run_dir = context.study_dir / str(trial.number)
    trial.set_user_attr("run_dir", str(run_dir))
    trial.set_user_attr("overrides", overrides)
    print(f"stages-tune: trial {trial.number}: {' '.join(overrides[len(base) :])}", flush=True)
    try:
        run_cfg = apply_all_stages(context.compose(overrides), keep=stage_keys_set(overrides))
        files: dict[str, Any] = {"config.yaml": run_cfg, "overrides.yaml": overrides}
        if context.hydra_cfg is not None:  # the command's, as this trial's job
            job = {"overrides": {"task": overrides}, "runtime": {"output_dir": str(run_dir)}}
            hydra_cfg = OmegaConf.merge(context.hydra_cfg, job, {"job": {"num": trial.number}})
            files["hydra.yaml"] = OmegaConf.create({"hydra": hydra_cfg})
        pruning = TrialPruning(trial, str(cfg.objective.direction))
        experiment = Experiment(run_cfg, run_dir, hydra_files=files, observers=[pruning])
    except RunDirError as err:
        raise StudyError(f"{err} (trial {trial.number})") from None
    except OSError as err:
        raise StudyError(f"cannot write {err.filename or run_dir}: {err.strerror or err}") from None
    except (ConfigError, HydraException, OmegaConfBaseException) as err:
        invalid = err if isinstance(err, ConfigError) else hydra_message(err)
        directory = RunDir(run_dir)  # the trial's own directory: the summary shows why
        directory.write_hydra_files({"overrides.yaml": overrides})
        directory.write_status("invalid", f"invalid config: {invalid}")
        raise TrialFailed(f"invalid config: {invalid}") from None
    try:  # how a run that does not finish ended is in its status.json (Experiment.run)
        results = experiment.run()
    except StopRun as err:
        print(f"stages-tune: trial {trial.number} {err}", flush=True)
        raise optuna.TrialPruned(str(err)) from None
    except Interrupted:
        raise
    except RUN_ERRORS as err:
        raise TrialFailed(str(err)) from None
    except Exception as err:  # the env's (or other user code's) own exception: its traceback
        traceback.print_exc()
        raise TrialFailed(one_line(err)) from None
    return experiment.report(results)


def _sqlite_file(storage: str) -> str | None:
    path = storage.removeprefix("sqlite:///")
    return path if path != storage and path not in ("", ":memory:") else None


def storage_location(storage: str, cwd: str | Path) -> str:
    """``tune.storage`` with a relative SQLite or journal file made absolute against ``cwd``."""
    if "://" not in storage:
        return str(Path(cwd) / Path(storage).expanduser())
    path = _sqlite_file(storage)
    return storage if path is None else "sqlite:///" + str(Path(cwd) / path)


def _load_study(cfg: DictConfig, location: str) -> Any:
    """The study, made or loaded, checked to optimize the objective; its sampler is seeded from
    ``tune.seed`` plus the trials it has, so that a rerun draws new values."""
    import optuna

    file = location if "://" not in location else _sqlite_file(location)
    if file is not None and not (folder := Path(file).parent).is_dir():
        fix = "make that directory first, or name a file in one that exists"
        check(False, "tune.storage", cfg.tune.storage, f"{folder} is not a directory", fix)
    storage: Any = location  # an RDB URL
    if "://" not in location:  # a journal file
        storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(file))
    tune, objective = cfg.tune, cfg.objective
    name, direction = str(tune.study_name), str(objective.direction)
    study = optuna.create_study(
        storage=storage, study_name=name, direction=direction, load_if_exists=True
    )
    theirs, metric = study.direction.name.lower(), study.user_attrs.get("objective.metric")
    where = f"the study in {tune.storage}"
    rule = f"{where} was made to {theirs} the objective, objective.direction={direction}"
    fix = "name a new study (tune.study_name=...) or keep objective.direction as the study's"
    check(theirs == direction, "tune.study_name", name, rule, fix)
    rule = f"{where} optimizes objective.metric={metric}, not {objective.metric}"
    fix = "name a new study (tune.study_name=...) or keep the study's objective.metric"
    check(metric in (None, objective.metric), "tune.study_name", name, rule, fix)
    if metric is None:
        study.set_user_attr("objective.metric", str(objective.metric))
    seed = int(tune.seed) + len(study.get_trials(deepcopy=False))
    samplers = optuna.samplers
    sampler = samplers.RandomSampler if tune.sampler == "random" else samplers.TPESampler
    study.sampler, study.pruner = sampler(seed=seed), make_pruner(tune, direction)
    return study


def _best(study: Any, cfg: DictConfig, location: str) -> dict[str, Any]:
    """What ``best.yaml`` holds: the study, its trials by state and its best trial."""
    counts = dict(Counter(t.state.name.lower() for t in study.get_trials(deepcopy=False)))
    objective = {"metric": str(cfg.objective.metric), "direction": study.direction.name.lower()}
    best = None
    if counts.get("complete"):
        trial = study.best_trial
        best = {"number": trial.number, "value": trial.value, "params": dict(trial.params)}
        best |= {key: trial.user_attrs.get(key) for key in ("run_dir", "overrides")}
    return {
        "study_name": study.study_name,
        "storage": location,
        "objective": objective,
        "trials": counts,
        "best": best,
    }


def run_study(cfg: DictConfig, context: StudyContext) -> int:
    """Runs ``tune.n_trials`` trials after checking the settings and every bound of the space
    (:class:`ConfigError`), writes the summary and ``best.yaml`` and prints the best trial.
    Returns the exit code: 1 when every trial of this command failed, else 0."""
    try:
        import optuna
    except ImportError:
        raise StudyError(
            "Optuna is not installed. Fix: pip install 'torchrl-stages[tune]' (or "
            "pip install 'optuna>=4,<6')"
        ) from None
    tune = cfg.tune
    space, base = checked_search(tune, context.overrides, context.compose)
    location = storage_location(str(tune.storage), context.cwd)
    try:
        study = _load_study(cfg, location)
    except ConfigError:
        raise
    except Exception as err:  # noqa: BLE001 - SQLAlchemy's, a database driver's, the disk's
        raise StudyError(
            f"cannot open the study in tune.storage={tune.storage} ({one_line(err)}). Fix: "
            "check the URL (sqlite:///study.db), its database driver, or the journal file's path"
        ) from None
    context.study_dir.mkdir(parents=True, exist_ok=True)
    mine: set[int] = set()  # another process may add trials to the same study meanwhile

    def objective(trial: Any) -> float:
        mine.add(trial.number)
        return _run_trial(trial, cfg, space, base, context)

    try:
        study.optimize(objective, n_trials=int(tune.n_trials), catch=(TrialFailed,))
    finally:
        failure = "stages-tune: no study summary"
        summary = summarize_or_say(context.study_dir, bool(tune.plots), failure)
        if summary is not None:
            print(f"Study summary: {summary.files['summary.md']}")
        best = _best(study, cfg, location)
        (context.study_dir / BEST_FILE).write_text(yaml.safe_dump(best, sort_keys=False))
    trials = study.get_trials(deepcopy=False)
    states = [t.state for t in trials if t.number in mine]
    state = optuna.trial.TrialState
    pruned, failed = states.count(state.PRUNED), states.count(state.FAIL)
    print(
        f"stages-tune: study {study.study_name}: {len(states)} trials run here "
        f"({len(states) - failed - pruned} finished, {pruned} pruned, {failed} failed), "
        f"{len(trials)} in the study"
    )
    if (top := best["best"]) is None:
        print("stages-tune: no trial of the study has finished yet")
    else:
        params = " ".join(f"{k}={hydra_value(v)}" for k, v in top["params"].items())
        print(f"Best trial {top['number']}: {cfg.objective.metric}={top['value']:g} with {params}")
        print(f"  run directory: {top['run_dir']}")
    print(f"Best trial file: {context.study_dir / BEST_FILE}")
    return EXIT_FAILED if states and failed == len(states) else 0
