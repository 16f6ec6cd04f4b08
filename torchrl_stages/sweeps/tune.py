"""``stages-tune``: hyper-parameter tuning with Optuna, each trial a ``stages-train`` run.

``stages-tune`` composes the config ``stages-train`` does (every override of it works) with a
``tune`` block (:class:`torchrl_stages.config.TuneConfig`): the study's name and storage, the
sampler and pruner, and the search space ``tune.params``. Trial ``n`` is the run
``stages-train`` would make with the command's overrides and the trial's values
(:class:`~torchrl_stages.experiment.Experiment`), written to ``<study dir>/<n>/`` with its
``.hydra/overrides.yaml``, where the study directory is the command's ``hydra.run.dir``. Each
stage evaluation's success rate is reported to the trial (:class:`TrialPruning`, an observer
of the run's logger); a trial the pruner finds hopeless stops there, ``status.json`` saying
``pruned``. At the end the study directory gets the sweep summary
(:func:`torchrl_stages.sweeps.summarize_sweep`) and ``best.yaml``.

Optuna is imported only when a study runs: this module loads without the ``[tune]`` extra.
"""

from __future__ import annotations

import copy
import math
import re
import sys
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import yaml
from hydra.core.hydra_config import HydraConfig
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
from torchrl_stages.experiment import Experiment, seed_dir
from torchrl_stages.failures import DivergenceError, EnvError, one_line
from torchrl_stages.loggers import StopRun
from torchrl_stages.preemption import Interrupted
from torchrl_stages.rundir import RunDir, RunDirError
from torchrl_stages.seed_run import with_env_stages
from torchrl_stages.store import config_group_options
from torchrl_stages.sweeps import find_jobs, summarize_sweep
from torchrl_stages.tasks import format_summary
from torchrl_stages.validate import validate_config

__all__ = [
    "ParamSpec",
    "StudyContext",
    "TrialPruning",
    "hydra_value",
    "run_study",
    "search_space",
    "storage_location",
    "train_overrides",
    "tune_app",
]

EXIT_FAILED, EXIT_INVALID = 1, 2  # those of stages-train
SAMPLERS = ("tpe", "random")
PRUNERS = ("median", "threshold", "none")
SPEC_KEYS = ("low", "high", "log", "step", "choices")
BEST_FILE = "best.yaml"
#: the metrics a stage evaluation logs its success rate as (backward and flat: ``stage_<k>``,
#: joint: ``joint_<k>``, phase k)
STAGE_EVALUATION = re.compile(r"^eval/(stage|joint)_\d+/success_rate$")
_PLAIN = re.compile(r"^[A-Za-z_][\w\-./@:]*$")
_MISSING = object()

#: ``compose(overrides)``: the config ``stages-train`` composes from ``overrides``
Compose = Callable[[list[str]], DictConfig]


class TrialFailed(RuntimeError):
    """A trial whose run did not finish (bad config, divergence, the env's error): recorded as
    failed in the study, which goes on with the next trial."""


class StudyError(RuntimeError):
    """The study cannot go on (a trial's directory holds another run, a disk error)."""


# ---------------------------------------------------------------------- the search space
def hydra_value(value: Any) -> str:
    """``value`` as a Hydra command-line value.

    Examples:
        >>> [hydra_value(v) for v in (3, 0.001, True, None, "sac", "a b")]
        ['3', '0.001', 'true', 'null', 'sac', "'a b'"]
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, int | float):
        return repr(value)
    text = str(value)
    if _PLAIN.match(text) and text.lower() not in ("true", "false", "null", "nan", "inf"):
        return text
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass
class ParamSpec:
    """One entry of ``tune.params``: a config key (or group) and its range.

    ``key`` is written as on the command line: ``task.stages.s3.lr``, ``+all_stages.lr`` (a key
    added to a mapping), ``algo@task.stages.s0`` (a config group); Optuna knows the parameter
    by :attr:`name`, the key without ``+``.

    Examples:
        >>> spec = ParamSpec.parse("task.stages.s3.lr", {"low": 1e-4, "high": 1e-2, "log": True})
        >>> spec.kind, spec.override(0.003), spec.candidates()
        ('float', 'task.stages.s3.lr=0.003', [0.0001, 0.01])
        >>> ParamSpec.parse("task.stages.s3.batch_size", {"low": 32, "high": 256}).kind
        'int'
        >>> ParamSpec.parse("algo@task.stages.s0", {"choices": ["dqn", "sac"]}).kind
        'categorical'
        >>> ParamSpec.parse("task.stages.s3.lr", {"low": 0.0, "high": 1e-2, "log": True})
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: tune.params.task.stages.s3.lr.low=0.0: ...
    """

    key: str
    kind: str  # float | int | categorical
    low: float | int | None = None
    high: float | int | None = None
    log: bool = False
    step: float | int | None = None
    choices: tuple[Any, ...] = ()

    @property
    def name(self) -> str:
        """The parameter's name in the study: the key without its leading ``+``."""
        return self.key.lstrip("+")

    @classmethod
    def parse(cls, key: str, spec: Any) -> ParamSpec:
        """The spec ``{low, high[, log][, step]}`` or ``{choices}`` of ``key``; a
        :class:`~torchrl_stages.config.ConfigError` names what is wrong and the fix."""
        where = f"tune.params.{key}"
        example = "{low: 1e-4, high: 1e-2, log: true} or {choices: [a, b]}"
        check(
            isinstance(spec, Mapping) and bool(spec),
            where,
            spec,
            f"a range is a mapping of {', '.join(SPEC_KEYS)}",
            f"write it as {example}",
        )
        unknown = [str(k) for k in spec if k not in SPEC_KEYS]
        check(
            not unknown,
            where,
            dict(spec),
            f"unknown {', '.join(unknown)} (known: {', '.join(SPEC_KEYS)})",
            f"write it as {example}",
        )
        if "choices" in spec:
            choices = spec["choices"]
            check(
                set(spec) == {"choices"},
                where,
                dict(spec),
                "choices cannot go with low, high, log or step",
                "keep either choices or the range",
            )
            ok = isinstance(choices, Sequence) and not isinstance(choices, str) and choices
            check(bool(ok), f"{where}.choices", choices, "must be a non-empty list", example)
            for choice in choices:
                check(
                    choice is None or isinstance(choice, bool | int | float | str),
                    f"{where}.choices",
                    list(choices),
                    f"{choice!r} is not a number, a string, a boolean or null",
                    "list plain values (a config group's options by name)",
                )
            return cls(key, "categorical", choices=tuple(choices))
        for bound in ("low", "high"):
            check(
                _is_number(spec.get(bound)),
                f"{where}.{bound}",
                spec.get(bound),
                "must be a finite number",
                f"write the range as {example}",
            )
        low, high, log, step = spec["low"], spec["high"], spec.get("log", False), spec.get("step")
        check(isinstance(log, bool), f"{where}.log", log, "must be true or false", "set log: true")
        check(low < high, f"{where}.low", low, f"must be below high={high}", "swap them")
        if log:
            check(low > 0, f"{where}.low", low, "must be > 0 with log: true", "set low > 0")
            check(step is None, f"{where}.step", step, "cannot go with log: true", "drop one")
        if step is not None:
            check(_is_number(step) and step > 0, f"{where}.step", step, "must be > 0", "fix it")
        is_int = all(isinstance(v, int) for v in (low, high, step if step is not None else 1))
        return cls(key, "int" if is_int else "float", low, high, log, step)

    def suggest(self, trial: Any) -> Any:
        """The trial's value (``trial``: an ``optuna.Trial``)."""
        if self.kind == "categorical":
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.kind == "int":
            step = 1 if self.step is None else int(self.step)
            return trial.suggest_int(self.name, self.low, self.high, step=step, log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, step=self.step, log=self.log)

    def override(self, value: Any) -> str:
        """The command-line override that sets ``value``."""
        return f"{self.key}={hydra_value(value)}"

    def candidates(self) -> list[Any]:
        """The values checked before any training: the bounds, or every choice."""
        return list(self.choices) if self.kind == "categorical" else [self.low, self.high]

    @property
    def group(self) -> str | None:
        """The config group the key selects an option of (``algo@task.stages.s0``: ``algo``),
        as far as its spelling says (``schedule`` is one too: see :func:`check_space`)."""
        path = self.name.split("@", 1)[0]
        return path if ("@" in self.name or "/" in path) else None


def _flatten(params: Mapping, prefix: str = "") -> Iterable[tuple[str, Any]]:
    for key, value in params.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        is_spec = (  # a range has low, high or choices (and no mapping in it)
            isinstance(value, Mapping)
            and bool({"low", "high", "choices"} & set(value))
            and not any(isinstance(v, Mapping) for v in value.values())
        )
        if isinstance(value, Mapping) and value and not is_spec:
            yield from _flatten(value, path)
        else:
            yield path, value


def search_space(params: Any) -> list[ParamSpec]:
    """``tune.params`` as specs: keys written with dots (``{task.stages.s3.lr: {...}}``) or
    nested (``+tune.params.task.stages.s3.lr={...}`` on the command line) alike.

    Examples:
        >>> space = search_space({"task.stages.s3.lr": {"low": 1e-4, "high": 1e-2, "log": True},
        ...                       "task": {"stages": {"s2": {"gamma": {"choices": [0.9, 0.99]}}}}})
        >>> [(p.name, p.kind) for p in space]
        [('task.stages.s3.lr', 'float'), ('task.stages.s2.gamma', 'categorical')]
    """
    if isinstance(params, DictConfig):
        params = OmegaConf.to_container(params, resolve=True)
    check(
        isinstance(params, Mapping) and bool(params),
        "tune.params",
        params,
        "the search space is empty",
        "add one range per key, e.g. 'tune.params={task.stages.s3.lr: {low: 1e-4, "
        "high: 1e-2, log: true}}'",
    )
    space = [ParamSpec.parse(key, spec) for key, spec in _flatten(params)]
    names = [p.name for p in space]
    for name in names:
        check(
            names.count(name) == 1,
            f"tune.params.{name}",
            "...",
            "given twice",
            "keep one",
        )
    return space


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def train_overrides(overrides: Iterable[str]) -> list[str]:
    """The command line's overrides that ``stages-train`` takes: all but the ``tune`` ones.

    Examples:
        >>> train_overrides(["experiment=smoke", "tune.n_trials=4", "+tune.params={}", "tune=lr"])
        ['experiment=smoke']
    """
    out = []
    for override in overrides:
        key = _override_key(override)
        if key != "tune" and not key.startswith("tune."):
            out.append(override)
    return out


# ---------------------------------------------------------------------- pruning
class TrialPruning:
    """An observer of a run's metrics (:data:`torchrl_stages.loggers.Observer`) that reports
    every stage evaluation's success rate to an Optuna ``trial`` and ends the run with
    :class:`~torchrl_stages.loggers.StopRun` (``pruned``) when the trial should be pruned.

    The step of a report is the evaluation's index in the run (0, 1, ...: the backward
    schedule evaluates the last stage first). With ``direction="minimize"`` (the objective's)
    it reports the failure rate ``1 - success``, so that lower is better there too.

    Examples:
        >>> class Trial:  # what it uses of an optuna.Trial
        ...     reported = []
        ...     def report(self, value, step):
        ...         self.reported.append((step, value))
        ...     def should_prune(self):
        ...         return len(self.reported) >= 2
        >>> trial = Trial()
        >>> pruning = TrialPruning(trial)
        >>> pruning({"eval/stage_4/success_rate": 0.5, "eval/stage_4/value_error": 0.1}, 512)
        >>> pruning({"train/stage_4/loss": 0.2}, 768)  # not an evaluation
        >>> pruning({"eval/stage_4/success_rate": 0.25}, 1024)
        Traceback (most recent call last):
        ...
        torchrl_stages.loggers.StopRun: pruned at stage evaluation 1 (...=0.25 at 1024 frames ...)
        >>> trial.reported
        [(0, 0.5), (1, 0.25)]
    """

    def __init__(self, trial: Any, direction: str = "maximize") -> None:
        self.trial = trial
        self.minimize = direction == "minimize"
        self.evaluations = 0

    def __call__(self, metrics: dict[str, float], step: int) -> None:
        for name, value in metrics.items():
            if STAGE_EVALUATION.match(name) is None:
                continue
            index, self.evaluations = self.evaluations, self.evaluations + 1
            success = float(value)
            self.trial.report(1.0 - success if self.minimize else success, index)
            if self.trial.should_prune():
                raise StopRun(
                    "pruned",
                    f"pruned at stage evaluation {index} ({name}={success:g} at {step} frames "
                    "of the stage)",
                )


def make_sampler(name: str, seed: int) -> Any:
    """The Optuna sampler ``tune.sampler`` names, seeded."""
    import optuna

    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed)


def make_pruner(tune: DictConfig, direction: str) -> Any:
    """The Optuna pruner ``tune.pruner`` names, over the values :class:`TrialPruning`
    reports (success rates; failure rates when the objective is minimized)."""
    import optuna

    warmup = int(tune.warmup_steps)
    if tune.pruner == "median":
        return optuna.pruners.MedianPruner(
            n_startup_trials=int(tune.startup_trials), n_warmup_steps=warmup
        )
    if tune.pruner == "threshold":
        below = float(tune.prune_below)
        if direction == "minimize":  # failure rates reported: above 1 - below is pruned
            return optuna.pruners.ThresholdPruner(upper=1.0 - below, n_warmup_steps=warmup)
        return optuna.pruners.ThresholdPruner(lower=below, n_warmup_steps=warmup)
    return optuna.pruners.NopPruner()


# ---------------------------------------------------------------------- storage
def storage_location(storage: str, cwd: str | Path) -> str:
    """``tune.storage`` with a relative SQLite file or journal file made absolute against
    ``cwd`` (where the command was launched); other URLs as given.

    Examples:
        >>> storage_location("sqlite:///study.db", "/runs")
        'sqlite:////runs/study.db'
        >>> storage_location("study.log", "/runs")
        '/runs/study.log'
        >>> storage_location("postgresql://host/optuna", "/runs")
        'postgresql://host/optuna'
    """
    if "://" not in storage:
        return str(Path(cwd) / Path(storage).expanduser())
    if storage.startswith("sqlite:///"):
        path = storage[len("sqlite:///") :]
        if path and path != ":memory:" and not Path(path).is_absolute():
            return "sqlite:///" + str(Path(cwd) / path)
    return storage


def open_storage(location: str) -> Any:
    """The Optuna storage at ``location`` (:func:`storage_location`): an RDB URL as is (a
    SQLite file's directory is created), a journal file as ``JournalStorage``."""
    import optuna

    if "://" in location:
        if location.startswith("sqlite:///") and location != "sqlite:///:memory:":
            Path(location[len("sqlite:///") :]).parent.mkdir(parents=True, exist_ok=True)
        return location
    Path(location).parent.mkdir(parents=True, exist_ok=True)
    return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(location))


# ---------------------------------------------------------------------- checks
def check_settings(tune: DictConfig) -> None:
    """Checks the ``tune`` keys other than ``params`` (:class:`ConfigError`)."""
    check(bool(tune.study_name), "tune.study_name", tune.study_name, "empty", "name the study")
    check(bool(tune.storage), "tune.storage", tune.storage, "empty", "set sqlite:///study.db")
    check(tune.n_trials >= 1, "tune.n_trials", tune.n_trials, "must be >= 1", "set it to 1+")
    for key, value, known in (
        ("sampler", tune.sampler, SAMPLERS),
        ("pruner", tune.pruner, PRUNERS),
    ):
        check(
            value in known,
            f"tune.{key}",
            value,
            f"unknown (known: {', '.join(known)})",
            f"set tune.{key}={known[0]}",
        )
    check(
        tune.startup_trials >= 0,
        "tune.startup_trials",
        tune.startup_trials,
        "must be >= 0",
        "set it to 0 or more",
    )
    check(
        tune.warmup_steps >= 0,
        "tune.warmup_steps",
        tune.warmup_steps,
        "must be >= 0",
        "set it to 0 or more",
    )
    if tune.pruner == "threshold":
        below = tune.prune_below
        check(
            below is not None and 0 < below <= 1,
            "tune.prune_below",
            below,
            "the threshold pruner needs a success rate in (0, 1]",
            "set tune.prune_below=0.1 (or another pruner)",
        )


def train_config(compose: Compose, overrides: list[str]) -> DictConfig:
    """The config of a run of ``overrides``, as ``stages-train`` makes it and checked as
    :class:`~torchrl_stages.experiment.Experiment` does before training (:class:`ConfigError`;
    Hydra's errors for overrides that do not compose)."""
    cfg = apply_all_stages(compose(overrides), keep=stage_keys_set(overrides))
    validate_config(with_env_stages(cfg))
    return cfg


def _compose_error(err: BaseException) -> str:
    """Hydra's message in one line, with its cause's (the indented details left out)."""
    parts, cause = [], err
    while cause is not None and len(parts) < 2:
        lines = [line for line in str(cause).splitlines() if line.strip() and not line[0].isspace()]
        parts.extend(lines[:1])
        cause = cause.__cause__
    return ": ".join(parts) if parts else type(err).__name__


def _fail(where: str, problem: str, fix: str) -> None:
    raise ConfigError(f"{where}: {problem}. Fix: {fix}")


def check_space(space: list[ParamSpec], base: list[str], compose: Compose) -> None:
    """Checks every entry of ``space`` against the config of ``base`` (the command line's
    overrides) before any training: the key exists (or the group and its options), no
    override of the command line sets it too, and each bound (each choice) makes a valid
    config. Raises :class:`ConfigError` naming the key and the fix."""
    try:
        cfg = train_config(compose, base)
    except (HydraException, OmegaConfBaseException) as err:
        message = f"the command's overrides do not compose: {_compose_error(err)}"
        raise ConfigError(message) from None
    set_by_command = {_override_key(o) for o in base}
    for spec in space:
        where = f"tune.params.{spec.key}"
        if spec.name.split(".")[0] in ("tune", "hydra"):
            _fail(
                where,
                "tune.* and hydra.* keys are not searched",
                "search keys of the run's config (stages-train --cfg job lists them)",
            )
        if spec.name in set_by_command:
            _fail(
                where,
                "the command line sets this key too",
                f"drop {spec.name}=... from the command line, or drop it from tune.params",
            )
        group = spec.group or spec.name
        options = config_group_options(group)
        if spec.group is not None or (options and "." not in spec.name):
            if not options:
                _fail(
                    where,
                    f"no config group '{group}'",
                    "name a group (algo@task.stages.<stage>, schedule, task/gammas) or a key",
                )
            if spec.kind != "categorical" or not all(c in options for c in spec.choices):
                _fail(
                    where,
                    f"a config group takes choices among its options ({', '.join(options)})",
                    f"write {{choices: [...]}} with some of {', '.join(options)}",
                )
        elif not spec.key.startswith("+"):
            node = OmegaConf.select(cfg, spec.name, default=_MISSING, throw_on_missing=False)
            if node is _MISSING:
                _fail(
                    where,
                    "no such key in the config",
                    "check its spelling (stages-train <your overrides> --cfg job prints the "
                    f"config), or write +{spec.name} to add a key to a mapping",
                )
            if OmegaConf.is_config(node):
                _fail(where, "names a block of keys, not one value", "name one key under it")
        for value in spec.candidates():
            override = spec.override(value)
            try:
                train_config(compose, [*base, override])
            except (HydraException, OmegaConfBaseException) as err:
                _fail(
                    where,
                    f"{override} does not fit the config ({_compose_error(err)})",
                    "give the key values of its type",
                )
            except ConfigError as err:
                problem = str(err).split(". Fix: ")[0]
                _fail(
                    where,
                    f"{override} makes an invalid config ({problem})",
                    "narrow the range to values the key accepts",
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
        invalid = err if isinstance(err, ConfigError) else _compose_error(err)
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


# ---------------------------------------------------------------------- the command
@hydra.main(config_path="pkg://torchrl_stages.conf", config_name="tune", version_base="1.3")
def tune_app(cfg: DictConfig) -> None:
    """``stages-tune [OVERRIDES...]`` (Hydra app; ``torchrl_stages.cli.tune`` registers the
    schemas first). Exit codes: 0 done, 1 every trial failed, 2 invalid config or a study that
    cannot go on, 128 + N stopped by signal N."""
    hydra_cfg = HydraConfig.get()

    def compose(overrides: list[str]) -> DictConfig:
        return hydra.compose(config_name="config", overrides=overrides)

    context = StudyContext(
        study_dir=Path(hydra_cfg.runtime.output_dir),
        cwd=Path(hydra_cfg.runtime.cwd),
        overrides=list(hydra_cfg.overrides.task),
        compose=compose,
        hydra_cfg=hydra_cfg,
    )
    try:
        code = run_study(cfg, context)
    except ConfigError as err:
        print(f"stages-tune: invalid config: {err}", file=sys.stderr)
        sys.exit(EXIT_INVALID)
    except StudyError as err:
        print(f"stages-tune: {err}", file=sys.stderr)
        sys.exit(EXIT_INVALID)
    except Interrupted as err:
        print(
            f"stages-tune: {err}; the trial is recorded as failed. Fix: run the same command "
            "again to go on with the study",
            file=sys.stderr,
        )
        sys.exit(err.exit_code)
    if code:
        print("stages-tune: every trial failed (their status.json say why)", file=sys.stderr)
        sys.exit(code)
