"""The bound every config field declares (:func:`positive`, :func:`one_of`, ...), the checks
generated from them and :class:`ConfigError`."""

from __future__ import annotations

import difflib
import functools
import re
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from omegaconf import MISSING, ListConfig, OmegaConf


class ConfigError(ValueError):
    """An invalid configuration, found before training starts."""

    __module__ = "torchrl_stages.config"  # where it is imported from


def check(ok: bool, key: str, value: object, rule: str, fix: str) -> None:
    """Raises :class:`ConfigError` ``"{key}={value!r}: {rule}. Fix: {fix}"`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{key}={value!r}: {rule}. Fix: {fix}")


@dataclass(frozen=True)
class Bound:
    """The values a config field accepts: a number in ``[low, high]``, one of ``choices``, a
    full match of ``pattern`` (``text`` names it), or any (``free``). A list needs one entry at
    least, each inside; ``None`` is left to the field's type.

    Examples:
        >>> Bound(low=0, low_open=True).problem(0), Bound(choices=("a", "b")).problem(["a"])
        ('must be > 0', None)
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[Any, ...] = ()
    pattern: str | None = None
    text: str = ""
    free: bool = False
    example: Any = None

    def rule(self) -> str:
        if self.choices:
            return f"unknown (known: {', '.join(map(str, self.choices))})"
        if self.pattern:
            return f"must be {self.text}"
        if self.high is None:
            return f"must be {'>' if self.low_open else '>='} {self.low}"
        left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
        return f"must be in {left}{self.low}, {self.high}{right}"

    def problem(self, value: Any) -> str | None:
        if self.free or value is None:
            return None
        if isinstance(value, list | ListConfig):
            if value and not any(map(self.problem, value)):
                return None
            return f"needs at least one entry, each {self.rule().removeprefix('must be ')}"
        if self.choices:
            ok = value in self.choices
        elif self.pattern:
            ok = re.fullmatch(self.pattern, str(value)) is not None
        else:
            above = value > self.low or (value == self.low and not self.low_open)
            below = self.high is None or value < self.high
            ok = above and (below or (value == self.high and not self.high_open))
        return None if ok else self.rule()

    def fix(self, key: str) -> str:
        shown = str(self.example).replace(" ", "")
        if self.example is None or shown == MISSING or "${" in shown or self.high is not None:
            return f"set {key} to a value in that range"
        return f"set {key}={shown}"


def bound(default: Any = MISSING, *, factory: Callable[[], Any] | None = None, **limits) -> Any:
    metadata = {"bound": Bound(**limits, example=factory() if factory else default)}
    if factory is not None:
        return field(default_factory=factory, metadata=metadata)
    return field(default=default, metadata=metadata)


def in_range(low: float, high: float, default: Any, **kwargs) -> Any:
    return bound(default, low=low, high=high, **kwargs)


def one_of(*choices: Any, default: Any) -> Any:
    return bound(default, choices=choices)


positive = functools.partial(bound, low=0, low_open=True)
non_negative = functools.partial(bound, low=0)
flag = functools.partial(bound, choices=(True, False))
free = functools.partial(bound, free=True)  # any value of the field's type (a name, a mapping)


def check_bounds(node: Any, schema: type, prefix: str, closed: bool = False) -> None:
    """Refuses every key of ``node`` (at ``prefix``) outside its ``schema`` field's bound; with
    ``closed``, every key the schema does not have too (Hydra lets ``+key=value`` add one)."""
    known = [f.name for f in fields(schema)]
    given = OmegaConf.to_container(node, resolve=False) if closed else {}  # as given
    for name, value in given.items():
        key = f"{prefix}.{name}" if prefix else name
        check_known(prefix, name, value, known, "a key of the config", f"drop {key}")
    for f in fields(schema):
        if f.name not in node or OmegaConf.is_missing(node, f.name):
            continue
        key, value = f"{prefix}.{f.name}" if prefix else f.name, node[f.name]
        if is_dataclass(f.default_factory) and value is not None:
            check_bounds(value, f.default_factory, key, closed)
        elif (bound := f.metadata.get("bound")) and (problem := bound.problem(value)):
            check(False, key, value, problem, bound.fix(key))


def nearest(name: str, known: Iterable[str]) -> str | None:
    return next(iter(difflib.get_close_matches(name, list(known), n=1)), None)


def check_known(
    prefix: str, name: str, value: object, known: Collection[str], what: str, fix: str
) -> None:
    """Refuses ``{prefix}.{name}``, not ``what`` (a key of dqn), unless ``name`` is in ``known``."""
    if name in known:
        return
    dot = f"{prefix}." if prefix else ""
    hint = f"did you mean {dot}{close}?" if (close := nearest(name, known)) else fix
    raise ConfigError(f"{dot}{name}={value!r}: not {what}. Fix: {hint}")


@dataclass
class StageChecks:
    """An algorithm's own checks that relate one stage's keys (``Learner.validate``).

    Examples:
        >>> checks = StageChecks("stages.s0", {"batch_size": 512})
        >>> checks(False, "batch_size", "must be <= buffer_size", "lower it")
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: stages.s0.batch_size=512: must be <= ... Fix: lower it
    """

    key: str
    cfg: Any

    def __call__(self, ok: bool, field: str, rule: str, fix: str) -> None:
        check(ok, f"{self.key}.{field}", self.cfg[field], rule, fix)
