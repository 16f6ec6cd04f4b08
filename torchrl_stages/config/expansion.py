"""A composed config before its checks: ``all_stages`` applied, ``task.stage_template`` expanded."""

from __future__ import annotations

import copy
from collections.abc import Iterable, Iterator
from dataclasses import fields, is_dataclass
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from torchrl_stages.config.bounds import ConfigError, nearest


def apply_all_stages(cfg: DictConfig, keep: Iterable[tuple[str, str]] = ()) -> DictConfig:
    """A copy of ``cfg`` with ``all_stages`` set in every stage but the ``(stage, key)`` pairs of
    ``keep`` (set on the command line), and ``all_stages`` emptied."""
    if not cfg.get("all_stages"):
        return cfg
    cfg = copy.deepcopy(cfg)
    every, kept = cfg.all_stages, set(keep)
    stages = dict(cfg.task.stages.items())
    if cfg.task.get("stage_template"):  # stages made from the template get them from there
        stages = {k: v for k, v in stages.items() if "algo" in v}
        stages["stage_template"] = cfg.task.stage_template
    for name, stage in stages.items():
        schema = OmegaConf.get_type(stage)
        known = [f.name for f in fields(schema)] if is_dataclass(schema) else None
        for key, value in every.items():
            if (name, key) in kept:
                continue
            try:
                if known is not None and key not in known:  # an open node would take it
                    raise ConfigKeyError(key)  # its schema does not
                stage[key] = value
            except OmegaConfBaseException as err:
                where = "task.stage_template" if name == "stage_template" else f"task.stages.{name}"
                fix = f"set it for the stages that have it (task.stages.<stage>.{key}=...)"
                if (close := nearest(key, known or ())) and close not in every:
                    fix = f"did you mean all_stages.{close}?"
                raise ConfigError(
                    f"all_stages.{key}={value!r}: {where} "
                    f"({getattr(schema, '__name__', schema)}) cannot take it "
                    f"({type(err).__name__}). Fix: {fix}"
                ) from None
    cfg.all_stages = {}
    return cfg


def expand_stage_template(task: DictConfig, num_stages: int) -> DictConfig:
    """The task with stages ``s0..s<num_stages-1>``, each the template with its own keys over it."""
    if not task.get("stage_template"):
        return task
    names = [f"s{k}" for k in range(num_stages)]
    if extra := [name for name in task.stages if name not in names]:
        raise ConfigError(
            f"task.stages.{extra[0]}: the env has {num_stages} stages, named "
            f"{', '.join(names)} (each task.stage_template with its own keys over it). Fix: "
            f"set that stage's keys as task.stages.<{names[0]}..{names[-1]}>.<key>=..."
        )
    task = copy.deepcopy(task)
    stages = {}
    for name in names:
        try:
            stages[name] = OmegaConf.merge(task.stage_template, task.stages.get(name) or {})
        except OmegaConfBaseException as err:
            raise ConfigError(
                f"task.stages.{name}: its keys do not fit task.stage_template "
                f"({type(err).__name__}: {str(err).splitlines()[0]}). Fix: set only keys the "
                "stage's algorithm has"
            ) from None
    with open_dict(task):
        task.stages = stages
    return task


def stage_keys_set(overrides: Iterable[str]) -> set[tuple[str, str]]:
    """The ``(stage, key)`` pairs that command-line ``overrides`` set directly.

    Examples:
        >>> sorted(stage_keys_set(["task.stages.s0.frames=10", "+task.stages.s1.lr=1e-3",
        ...                        "algo@task.stages.s2=sac", "seed=1"]))
        [('s0', 'frames'), ('s1', 'lr')]
    """
    keys = [override_key(override) for override in overrides]
    paths = [key.split(".") for key in keys if key.startswith("task.stages.") and "@" not in key]
    return {(path[2], path[3]) for path in paths if len(path) >= 4}


def override_key(override: str) -> str:
    """The key a command-line override sets (``+a.b=1``: ``a.b``)."""
    return override.split("=", 1)[0].lstrip("+~")


def leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of every leaf under the plain container ``node``."""
    if isinstance(node, dict | list):
        for key, item in node.items() if isinstance(node, dict) else enumerate(node):
            yield from leaves(item, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, node


def targets(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, value)`` of every ``_target_`` under the plain container ``node``.

    Examples:
        >>> list(targets({"task": {"env": {"_target_": "a.B", "fn": {"_target_": "a.f"}}}}))
        [('task.env._target_', 'a.B'), ('task.env.fn._target_', 'a.f')]
    """
    return ((key, value) for key, value in leaves(node, prefix) if f".{key}".endswith("._target_"))
