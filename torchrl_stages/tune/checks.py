"""A study's settings and search space checked before any trial runs: a bad one is refused
in one line naming the key and the fix."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.config import (
    ConfigError,
    apply_all_stages,
    check,
    stage_keys_set,
    validate_config,
)
from torchrl_stages.config.bounds import check_bounds
from torchrl_stages.config.registration import config_group_options
from torchrl_stages.config.schema import TuneConfig
from torchrl_stages.learners import ALGORITHMS, learner_class
from torchrl_stages.runs.seed_run import with_env_stages
from torchrl_stages.schedules import get_schedule
from torchrl_stages.tune.space import (
    PRUNERS,
    SAMPLERS,
    Compose,
    ParamSpec,
    override_key,
)

_MISSING = object()


# ---------------------------------------------------------------------- checks
def check_settings(tune: DictConfig) -> None:
    """Checks the ``tune`` keys other than ``params`` (:class:`ConfigError`)."""
    check_bounds(tune, TuneConfig, "tune")
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
    :class:`~torchrl_stages.runs.experiment.Experiment` does before training (:class:`ConfigError`;
    Hydra's errors for overrides that do not compose)."""
    cfg = apply_all_stages(compose(overrides), keep=stage_keys_set(overrides))
    schedule = get_schedule(str(cfg.schedule.name))
    validate_config(with_env_stages(cfg), schedule, learner_class, ALGORITHMS)
    return cfg


def compose_error(err: BaseException) -> str:
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
        message = f"the command's overrides do not compose: {compose_error(err)}"
        raise ConfigError(message) from None
    set_by_command = {override_key(o) for o in base}
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
                    f"{override} does not fit the config ({compose_error(err)})",
                    "give the key values of its type",
                )
            except ConfigError as err:
                problem = str(err).split(". Fix: ")[0]
                _fail(
                    where,
                    f"{override} makes an invalid config ({problem})",
                    "narrow the range to values the key accepts",
                )


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
