"""A study's settings and search space, checked before any trial runs."""

from __future__ import annotations

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
from torchrl_stages.config.expansion import override_key
from torchrl_stages.config.registration import config_group_options
from torchrl_stages.config.schema import TuneConfig
from torchrl_stages.learners import ALGORITHMS, learner_class
from torchrl_stages.runs.seed_run import with_env_stages
from torchrl_stages.schedules import get_schedule
from torchrl_stages.tune.space import Compose, ParamSpec

_MISSING = object()


def check_settings(tune: DictConfig) -> None:
    """Checks the ``tune`` keys other than ``params``: their bounds, then what relates them."""
    check_bounds(tune, TuneConfig, "tune")
    check(bool(tune.study_name), "tune.study_name", tune.study_name, "empty", "name the study")
    check(bool(tune.storage), "tune.storage", tune.storage, "empty", "set sqlite:///study.db")
    check(
        tune.pruner != "threshold" or tune.prune_below is not None,
        "tune.prune_below",
        tune.prune_below,
        "the threshold pruner needs a success rate in (0, 1]",
        "set tune.prune_below=0.1 (or another pruner)",
    )


def train_config(compose: Compose, overrides: list[str]) -> DictConfig:
    """The config of a run of ``overrides``, made and checked as ``stages-train`` does."""
    cfg = apply_all_stages(compose(overrides), keep=stage_keys_set(overrides))
    schedule = get_schedule(str(cfg.schedule.name))
    validate_config(with_env_stages(cfg), schedule, learner_class, ALGORITHMS)
    return cfg


def compose_error(err: BaseException) -> str:
    """Hydra's message in one line, with its cause's (without the indented details)."""
    parts, cause = [], err
    while cause is not None and len(parts) < 2:
        lines = [line for line in str(cause).splitlines() if line.strip() and not line[0].isspace()]
        parts.extend(lines[:1])
        cause = cause.__cause__
    return ": ".join(parts) if parts else type(err).__name__


def _fail(where: str, problem: str, fix: str) -> None:
    raise ConfigError(f"{where}: {problem}. Fix: {fix}")


def check_space(space: list[ParamSpec], base: list[str], compose: Compose) -> None:
    """Checks each entry of ``space`` against the config of the command's overrides ``base``:
    the key or group exists, the command does not set it, each bound or choice is valid."""
    try:
        cfg = train_config(compose, base)
    except (HydraException, OmegaConfBaseException) as err:
        message = f"the command's overrides do not compose: {compose_error(err)}"
        raise ConfigError(message) from None
    set_by_command = {override_key(o) for o in base}
    for spec in space:
        where = f"tune.params.{spec.key}"
        if spec.name.split(".")[0] in ("tune", "hydra"):
            fix = "search keys of the run's config (stages-train --cfg job lists them)"
            _fail(where, "tune.* and hydra.* keys are not searched", fix)
        if spec.name in set_by_command:
            fix = f"drop {spec.name}=... from the command line, or drop it from tune.params"
            _fail(where, "the command line sets this key too", fix)
        group = spec.group or spec.name
        options = config_group_options(group)
        if spec.group is not None or (options and "." not in spec.name):
            if not options:
                fix = "name a group (algo@task.stages.<stage>, schedule, task/gammas) or a key"
                _fail(where, f"no config group '{group}'", fix)
            if spec.kind != "categorical" or not all(c in options for c in spec.choices):
                known = ", ".join(options)
                problem = f"a config group takes choices among its options ({known})"
                _fail(where, problem, f"write {{choices: [...]}} with some of {known}")
        elif not spec.key.startswith("+"):
            node = OmegaConf.select(cfg, spec.name, default=_MISSING, throw_on_missing=False)
            if node is _MISSING:
                fix = (
                    "check its spelling (stages-train <your overrides> --cfg job prints the "
                    f"config), or write +{spec.name} to add a key to a mapping"
                )
                _fail(where, "no such key in the config", fix)
            if OmegaConf.is_config(node):
                _fail(where, "names a block of keys, not one value", "name one key under it")
        for value in spec.candidates():
            override = spec.override(value)
            try:
                train_config(compose, [*base, override])
            except (HydraException, OmegaConfBaseException) as err:
                problem = f"{override} does not fit the config ({compose_error(err)})"
                _fail(where, problem, "give the key values of its type")
            except ConfigError as err:
                problem = f"{override} makes an invalid config ({str(err).split('. Fix: ')[0]})"
                _fail(where, problem, "narrow the range to values the key accepts")
