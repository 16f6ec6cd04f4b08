"""``stages-tune``: hyper-parameter tuning with Optuna, each trial a ``stages-train`` run.

``stages-tune`` composes the config ``stages-train`` does (every override of it works) with a
``tune`` block (:class:`torchrl_stages.config.TuneConfig`): the study's name and storage, the
sampler and pruner, and the search space ``tune.params``. Trial ``n`` is the run
``stages-train`` would make with the command's overrides and the trial's values
(:class:`~torchrl_stages.runs.experiment.Experiment`), written to ``<study dir>/<n>/`` with its
``.hydra/overrides.yaml``, where the study directory is the command's ``hydra.run.dir``. Each
stage evaluation's success rate is reported to the trial (:class:`TrialPruning`, an observer
of the run's logger); a trial the pruner finds hopeless stops there, ``status.json`` saying
``pruned``. At the end the study directory gets the sweep summary
(:func:`torchrl_stages.sweeps.summarize_sweep`) and ``best.yaml``.

Optuna is imported only when a study runs: this module loads without the ``[tune]`` extra."""

from __future__ import annotations

import copy
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.checkpoint import CheckpointDamagedError
from torchrl_stages.config import (
    ConfigError,
    apply_all_stages,
    check,
    objective_value,
    stage_keys_set,
)
from torchrl_stages.failures import EXIT_FAILED, DivergenceError, EnvError, one_line
from torchrl_stages.loggers import StopRun
from torchrl_stages.preemption import Interrupted
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.evaluation import format_summary
from torchrl_stages.runs.experiment import Experiment, seed_dir
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.sweeps import find_jobs, summarize_sweep
from torchrl_stages.tune.checks import (
    check_settings,
    check_space,
    compose_error,
    open_storage,
    storage_location,
)
from torchrl_stages.tune.pruning import TrialPruning, make_pruner, make_sampler
from torchrl_stages.tune.space import (
    BEST_FILE,
    Compose,
    ParamSpec,
    StudyError,
    TrialFailed,
    hydra_value,
    search_space,
    train_overrides,
)


# ---------------------------------------------------------------------- the study
@dataclass
class StudyContext:
    """Where a study runs: its directory (the command's ``hydra.run.dir``), the directory
    the command was launched from, the command's overrides, how configs are composed and what
    each trial's ``.hydra/hydra.yaml`` records of Hydra (``None``: nothing).

    Examples:
        >>> context = StudyContext(Path("tune/grid"), Path("."), ["tune.n_trials=4"], print)
        >>> context.study_dir / "0", train_overrides(context.overrides)
        (PosixPath('tune/grid/0'), [])
    """

    study_dir: Path
    cwd: Path
    overrides: list[str]
    compose: Compose
    hydra_cfg: DictConfig | None = None


def _trial_hydra_files(
    context: StudyContext, cfg: DictConfig, overrides: list[str], run_dir: Path, number: int
) -> dict[str, Any]:
    files: dict[str, Any] = {"config.yaml": cfg, "overrides.yaml": overrides}
    if context.hydra_cfg is not None:
        hydra_cfg = copy.deepcopy(context.hydra_cfg)
        with read_write(hydra_cfg), open_dict(hydra_cfg):
            hydra_cfg.overrides.task = overrides
            hydra_cfg.runtime.output_dir = str(run_dir)
            hydra_cfg.job.num = number
        files["hydra.yaml"] = OmegaConf.create({"hydra": hydra_cfg})
    return files


def _run_trial(
    trial: Any, cfg: DictConfig, space: list[ParamSpec], base: list[str], context: StudyContext
) -> float:
    """Trial ``trial.number``: the run of the command's overrides and the trial's values."""
    import optuna

    overrides = [*base, *(spec.override(spec.suggest(trial)) for spec in space)]
    run_dir = context.study_dir / str(trial.number)
    trial.set_user_attr("run_dir", str(run_dir))
    trial.set_user_attr("overrides", overrides)
    print(f"stages-tune: trial {trial.number}: {' '.join(overrides[len(base) :])}", flush=True)
    invalid = None
    try:
        run_cfg = apply_all_stages(context.compose(overrides), keep=stage_keys_set(overrides))
    except (ConfigError, HydraException, OmegaConfBaseException) as err:
        invalid = err if isinstance(err, ConfigError) else compose_error(err)
    else:
        files = _trial_hydra_files(context, run_cfg, overrides, run_dir, trial.number)
        try:
            experiment = Experiment(
                run_cfg,
                run_dir,
                hydra_files=files,
                observers=[TrialPruning(trial, str(cfg.objective.direction))],
            )
        except RunDirError as err:
            raise StudyError(f"{err} (trial {trial.number})") from None
        except ConfigError as err:
            invalid = err
        except OSError as err:
            where = err.filename or run_dir
            raise StudyError(f"cannot write {where}: {err.strerror or err}") from None
    if invalid is not None:  # the trial's own directory: the summary shows why
        directory = RunDir(run_dir)
        directory.write_hydra_files({"overrides.yaml": overrides})
        directory.write_status("invalid", f"invalid config: {invalid}")
        raise TrialFailed(f"invalid config: {invalid}")
    try:  # how a run that does not finish ended is in its status.json (Experiment.run)
        results = experiment.run()
    except StopRun as err:
        print(f"stages-tune: trial {trial.number} {err}", flush=True)
        raise optuna.TrialPruned(str(err)) from None
    except Interrupted:
        raise
    except (DivergenceError, EnvError, RunDirError, CheckpointDamagedError) as err:
        raise TrialFailed(str(err)) from None
    except Exception as err:  # the env's (or other user code's) own exception: its traceback
        traceback.print_exc()
        raise TrialFailed(one_line(err)) from None
    for seed, result in zip(experiment.seeds, results, strict=True):
        where = seed_dir(run_dir, seed) if experiment.stacked else run_dir
        print(format_summary(result, where), flush=True)
    values = [objective_value(result, cfg) for result in results]
    return sum(values) / len(values)  # several seeds: the mean of their objectives


def _load_study(cfg: DictConfig, location: str) -> Any:
    """Creates the study, or loads it with its sampler (seeded from ``tune.seed`` and the
    trials it has) and pruner; checks that it optimizes the objective."""
    import optuna

    tune, objective = cfg.tune, cfg.objective
    storage = open_storage(location)
    name, direction = str(tune.study_name), str(objective.direction)
    study = optuna.create_study(
        storage=storage, study_name=name, direction=direction, load_if_exists=True
    )
    theirs = study.direction.name.lower()
    check(
        theirs == direction,
        "tune.study_name",
        name,
        f"the study in {tune.storage} was made to {theirs} the objective, "
        f"objective.direction={direction}",
        "name a new study (tune.study_name=...) or keep objective.direction as the study's",
    )
    metric = study.user_attrs.get("objective.metric")
    check(
        metric in (None, objective.metric),
        "tune.study_name",
        name,
        f"the study in {tune.storage} optimizes objective.metric={metric}, not {objective.metric}",
        "name a new study (tune.study_name=...) or keep the study's objective.metric",
    )
    if metric is None:
        study.set_user_attr("objective.metric", str(objective.metric))
    seed = int(tune.seed) + len(study.get_trials(deepcopy=False))
    return optuna.load_study(
        study_name=name,
        storage=storage,
        sampler=make_sampler(str(tune.sampler), seed),
        pruner=make_pruner(tune, direction),
    )


def _best(study: Any, cfg: DictConfig, location: str) -> dict[str, Any]:
    """What ``best.yaml`` holds: the study, its trials by state and its best trial."""
    import optuna

    states = [t.state for t in study.get_trials(deepcopy=False)]
    counts = {s.name.lower(): states.count(s) for s in optuna.trial.TrialState if s in states}
    out: dict[str, Any] = {
        "study_name": study.study_name,
        "storage": location,
        "objective": {
            "metric": str(cfg.objective.metric),
            "direction": study.direction.name.lower(),
        },
        "trials": counts,
        "best": None,
    }
    if counts.get("complete"):
        best = study.best_trial
        out["best"] = {
            "number": best.number,
            "value": best.value,
            "params": dict(best.params),
            "run_dir": best.user_attrs.get("run_dir"),
            "overrides": best.user_attrs.get("overrides"),
        }
    return out


def run_study(cfg: DictConfig, context: StudyContext) -> int:
    """Runs ``cfg.tune.n_trials`` trials of the study ``cfg.tune`` describes, writes the
    summary and ``best.yaml`` into the study directory and prints the best trial; returns the
    exit code (0; 1 when every trial of this command failed). The config, the search space
    and every bound of it are checked first (:class:`ConfigError`, before any training);
    :class:`StudyError` and :class:`~torchrl_stages.preemption.Interrupted` end the study."""
    try:
        import optuna
    except ImportError:
        raise StudyError(
            "Optuna is not installed. Fix: pip install 'torchrl-stages[tune]' (or "
            "pip install 'optuna>=4,<6')"
        ) from None
    tune = cfg.tune
    check_settings(tune)
    space = search_space(tune.params)
    base = train_overrides(context.overrides)
    check_space(space, base, context.compose)
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
    before = len(study.get_trials(deepcopy=False))
    context.study_dir.mkdir(parents=True, exist_ok=True)
    try:
        study.optimize(
            lambda trial: _run_trial(trial, cfg, space, base, context),
            n_trials=int(tune.n_trials),
            catch=(TrialFailed,),
        )
    finally:
        _summarize(context.study_dir, plots=bool(tune.plots))
        best = _best(study, cfg, location)
        (context.study_dir / BEST_FILE).write_text(yaml.safe_dump(best, sort_keys=False))
    ran = study.get_trials(deepcopy=False)[before:]
    states = [t.state for t in ran]
    failed = states.count(optuna.trial.TrialState.FAIL)
    print(
        f"stages-tune: study {study.study_name}: {len(ran)} trials run here "
        f"({len(ran) - failed - states.count(optuna.trial.TrialState.PRUNED)} finished, "
        f"{states.count(optuna.trial.TrialState.PRUNED)} pruned, {failed} failed), "
        f"{len(study.get_trials(deepcopy=False))} in the study"
    )
    if best["best"] is None:
        print("stages-tune: no trial of the study has finished yet")
    else:
        b = best["best"]
        params = " ".join(f"{k}={hydra_value(v)}" for k, v in b["params"].items())
        print(f"Best trial {b['number']}: {cfg.objective.metric}={b['value']:g} with {params}")
        print(f"  run directory: {b['run_dir']}")
    print(f"Best trial file: {context.study_dir / BEST_FILE}")
    return EXIT_FAILED if ran and failed == len(ran) else 0


def _summarize(study_dir: Path, plots: bool) -> None:
    """The sweep summary of the trials in ``study_dir`` (best effort: it never hides the
    study's own outcome)."""
    if not find_jobs(study_dir):
        return
    try:
        summary = summarize_sweep(study_dir, plots=plots)
    except Exception as err:  # noqa: BLE001
        print(f"stages-tune: no study summary ({type(err).__name__}: {err})", file=sys.stderr)
        return
    print(f"Study summary: {summary.files['summary.md']}")
