"""A study's settings and search space (``tune.params`` as :class:`ParamSpec` s, values as
overrides), checked before any trial runs."""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.config import ConfigError, apply_all_stages, check, stage_keys_set
from torchrl_stages.config.bounds import check_bounds
from torchrl_stages.config.checks import validate_config
from torchrl_stages.config.expansion import override_key
from torchrl_stages.config.registration import config_group_options, hydra_message
from torchrl_stages.config.schema import TuneConfig
from torchrl_stages.learners import ALGORITHMS, learner_class
from torchrl_stages.runs.seed_run import with_env_stages
from torchrl_stages.schedules import get_schedule

SPEC_KEYS = ("low", "high", "log", "step", "choices")
_MISSING = object()
_PLAIN = re.compile(r"^[A-Za-z_][\w\-./@:]*$")

#: ``compose(overrides)``: the config ``stages-train`` composes from ``overrides``
Compose = Callable[[list[str]], DictConfig]


def hydra_value(value: Any) -> str:
    """``value`` as a Hydra command-line value."""
    if value is None or isinstance(value, bool):
        return json.dumps(value)  # null, true, false
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
    """One entry of ``tune.params``: a key as written on the command line (``task.stages.s3.lr``,
    ``+all_stages.lr``, a group ``algo@task.stages.s0``) and its range; the study knows it by
    :attr:`name`, the key without ``+``.

    Examples:
        >>> spec = ParamSpec.parse("task.stages.s3.lr", {"low": 1e-4, "high": 1e-2, "log": True})
        >>> spec.kind, spec.override(0.003), spec.candidates()
        ('float', 'task.stages.s3.lr=0.003', [0.0001, 0.01])
        >>> ParamSpec.parse("algo@task.stages.s0", {"choices": ["dqn", "sac"]}).group
        'algo'
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
        return self.key.lstrip("+")

    @property
    def group(self) -> str | None:
        """The config group the key's spelling names (``algo@task.stages.s0``: ``algo``)."""
        path = self.name.split("@", 1)[0]
        return path if ("@" in self.name or "/" in path) else None

    @classmethod
    def parse(cls, key: str, spec: Any) -> ParamSpec:
        """The spec ``{low, high[, log][, step]}`` or ``{choices}`` of ``key``."""
        where = f"tune.params.{key}"
        example = "{low: 1e-4, high: 1e-2, log: true} or {choices: [a, b]}"
        rule = f"a range is a mapping of {', '.join(SPEC_KEYS)}"
        check(isinstance(spec, Mapping) and bool(spec), where, spec, rule, f"write it as {example}")
        unknown = ", ".join(str(k) for k in spec if k not in SPEC_KEYS)
        rule = f"unknown {unknown} (known: {', '.join(SPEC_KEYS)})"
        check(not unknown, where, dict(spec), rule, f"write it as {example}")
        if "choices" in spec:
            choices = spec["choices"]
            rule = "choices cannot go with low, high, log or step"
            fix = "keep either choices or the range"
            check(set(spec) == {"choices"}, where, dict(spec), rule, fix)
            listed = isinstance(choices, Sequence) and not isinstance(choices, str) and choices
            plain = listed and all(c is None or isinstance(c, int | float | str) for c in choices)
            rule = "must be a non-empty list of numbers, strings, booleans or nulls"
            check(bool(plain), f"{where}.choices", choices, rule, f"write it as {example}")
            return cls(key, "categorical", choices=tuple(choices))
        rule, fix = "must be a finite number", f"write the range as {example}"
        for bound in ("low", "high"):
            check(_is_number(spec.get(bound)), f"{where}.{bound}", spec.get(bound), rule, fix)
        low, high, log, step = spec["low"], spec["high"], spec.get("log", False), spec.get("step")
        for ok, name, value, rule, fix in (
            (isinstance(log, bool), "log", log, "must be true or false", "set log: true"),
            (low < high, "low", low, f"must be below high={high}", "swap them"),
            (not log or low > 0, "low", low, "must be > 0 with log: true", "set low > 0"),
            (not log or step is None, "step", step, "cannot go with log: true", "drop one"),
            (step is None or _is_number(step) and step > 0, "step", step, "must be > 0", "fix it"),
        ):
            check(ok, f"{where}.{name}", value, rule, fix)
        is_int = all(isinstance(v, int) for v in (low, high, step if step is not None else 1))
        return cls(key, "int" if is_int else "float", low, high, log, step)

    def suggest(self, trial: Any) -> Any:
        """The value of an ``optuna.Trial``."""
        if self.kind == "categorical":
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.kind == "int":
            step = 1 if self.step is None else int(self.step)
            return trial.suggest_int(self.name, self.low, self.high, step=step, log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, step=self.step, log=self.log)

    def override(self, value: Any) -> str:
        return f"{self.key}={hydra_value(value)}"

    def candidates(self) -> list[Any]:
        """The values checked before any training: the bounds, or every choice."""
        return list(self.choices) if self.kind == "categorical" else [self.low, self.high]


def _flatten(params: Mapping, prefix: str = "") -> Iterable[tuple[str, Any]]:
    for key, value in params.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        mapping = isinstance(value, Mapping) and bool(value)
        # a range has low, high or choices, and no mapping in it
        nested = mapping and any(isinstance(item, Mapping) for item in value.values())
        if mapping and (nested or not {"low", "high", "choices"} & set(value)):
            yield from _flatten(value, path)
        else:
            yield path, value


def search_space(params: Any) -> list[ParamSpec]:
    """``tune.params`` as specs, keys written with dots or nested alike."""
    if isinstance(params, DictConfig):
        params = OmegaConf.to_container(params, resolve=True)
    example = "tune.params={task.stages.s3.lr: {low: 1e-4, high: 1e-2, log: true}}"
    rule, fix = "the search space is empty", f"add one range per key, e.g. '{example}'"
    check(isinstance(params, Mapping) and bool(params), "tune.params", params, rule, fix)
    space = [ParamSpec.parse(key, spec) for key, spec in _flatten(params)]
    for name, count in Counter(spec.name for spec in space).items():
        check(count == 1, f"tune.params.{name}", "...", "given twice", "keep one")
    return space


def train_overrides(overrides: Iterable[str]) -> list[str]:
    """The command line's overrides that ``stages-train`` takes: all but the ``tune`` ones."""
    return [o for o in overrides if override_key(o).split(".")[0] != "tune"]


def check_settings(tune: DictConfig) -> None:
    """Checks the ``tune`` keys other than ``params``: their bounds, then what relates them."""
    check_bounds(tune, TuneConfig, "tune")
    check(bool(tune.study_name), "tune.study_name", tune.study_name, "empty", "name the study")
    check(bool(tune.storage), "tune.storage", tune.storage, "empty", "set sqlite:///study.db")
    needed = tune.pruner == "threshold" and tune.prune_below is None
    rule = "the threshold pruner needs a success rate in (0, 1]"
    fix = "set tune.prune_below=0.1 (or another pruner)"
    check(not needed, "tune.prune_below", tune.prune_below, rule, fix)


def train_config(compose: Compose, overrides: list[str]) -> DictConfig:
    """The config of a run of ``overrides``, made and checked as ``stages-train`` does."""
    cfg = apply_all_stages(compose(overrides), keep=stage_keys_set(overrides))
    schedule = get_schedule(str(cfg.schedule.name))
    validate_config(with_env_stages(cfg), schedule, learner_class, ALGORITHMS)
    return cfg


def _fail(where: str, problem: str, fix: str) -> None:
    raise ConfigError(f"{where}: {problem}. Fix: {fix}")


def checked_search(
    tune: DictConfig, overrides: list[str], compose: Compose
) -> tuple[list[ParamSpec], list[str]]:
    """The search space and the overrides every trial starts from, checked: the ``tune`` settings,
    then each entry's key or group, not set by the command, and each bound or choice of it."""
    check_settings(tune)
    space, base = search_space(tune.params), train_overrides(overrides)
    try:
        cfg = train_config(compose, base)
    except (HydraException, OmegaConfBaseException) as err:
        raise ConfigError(f"the command's overrides do not compose: {hydra_message(err)}") from None
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
                problem = f"{override} does not fit the config ({hydra_message(err)})"
                _fail(where, problem, "give the key values of its type")
            except ConfigError as err:
                problem = f"{override} makes an invalid config ({str(err).split('. Fix: ')[0]})"
                _fail(where, problem, "narrow the range to values the key accepts")
    return space, base
