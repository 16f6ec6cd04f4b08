"""Hydra's ConfigStore: the root schemas and the schema of every registered algorithm.

``conf/config.yaml`` (``stages-train``) extends ``train_schema``, ``conf/tune.yaml``
(``stages-tune``) ``tune_schema`` (the same keys and the ``tune`` block).
``conf/algo/<name>.yaml`` extends ``<name>_schema`` (the algorithm's config dataclass, see
:data:`torchrl_stages.learners.ALGORITHMS`), so ``algo@task.stages.<stage>=<name>`` composes a
stage from its algorithm's keys and defaults. The ``stages_algorithms`` resolver lists the
registered algorithms and ``stages_options`` the options of a config group (what ``conf/`` and
any config directory of yours hold), so that ``stages-train --help`` lists what there is.
``stages_by_prefix`` gives a key a value that depends on an id (a task's settings per level).

Hydra closes every mapping of a composed config, so that a key it lacks needs ``+``. Three kinds
of node stay open, so that one form of a key works on every task: ``task.stages`` (a template
task, ``task=gym``, has no stage before the env is built, yet ``task.stages.s2.lr=1e-3`` sets
one), each stage's keys (its algorithm's schema) and ``task.env`` (the env's own arguments, e.g.
``task.env.size=10`` for ``task=custom``). What they are given is checked before training
instead, with a one-line error naming the key and the nearest valid one
(:func:`torchrl_stages.validate.validate_config`).
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config import LoggerConfig, ScheduleConfig, TrainConfig, TuneAppConfig
from torchrl_stages.learners import ALGORITHMS


def register_configs() -> None:
    """Registers the schemas in Hydra's ConfigStore (YAML files extend them by name).

    Examples:
        >>> register_configs()
        >>> from hydra.core.config_store import ConfigStore
        >>> "dqn_schema.yaml" in ConfigStore.instance().repo["algo"]
        True
    """
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=_open(TrainConfig, "task.stages", "task.env"))
    # stages-tune's root (conf/tune.yaml)
    cs.store(name="tune_schema", node=_open(TuneAppConfig, "task.stages", "task.env"))
    cs.store(group="logger", name="logger_schema", node=LoggerConfig)
    cs.store(group="schedule", name="schedule_schema", node=ScheduleConfig)
    for name, learner in ALGORITHMS.items():
        cs.store(group="algo", name=f"{name}_schema", node=_open(learner.Config, ""))
    if not OmegaConf.has_resolver("stages_algorithms"):
        OmegaConf.register_new_resolver("stages_algorithms", lambda: "|".join(ALGORITHMS))
    if not OmegaConf.has_resolver("stages_options"):
        OmegaConf.register_new_resolver("stages_options", group_options)
    if not OmegaConf.has_resolver("stages_by_prefix"):
        OmegaConf.register_new_resolver("stages_by_prefix", by_prefix)


def _open(schema: type, *keys: str) -> DictConfig:
    """``schema`` as a config whose nodes at ``keys`` (``""``: the root) take keys they lack
    without Hydra's ``+``: their flag survives composition, where Hydra closes the rest."""
    node = OmegaConf.structured(schema)
    for key in keys:
        OmegaConf.set_struct(node if not key else OmegaConf.select(node, key), False)
    return node


def by_prefix(name: str, values: Mapping[str, Any], default: Any) -> Any:
    """The value in ``values`` of the first key that ``name`` starts with; ``default`` when none
    does. As the ``stages_by_prefix`` resolver it gives a config key a value per level, by the
    start of the level's id, which a command-line override of the key still replaces::

        view_doors: ${stages_by_prefix:${.env_id},{MiniGrid-KeyCorridor: true},false}

    Examples:
        >>> by_prefix("MiniGrid-KeyCorridorS3R3-v0", {"MiniGrid-KeyCorridor": 0.95}, 0.99)
        0.95
        >>> by_prefix("MiniGrid-DoorKey-8x8-v0", {"MiniGrid-KeyCorridor": 0.95}, 0.99)
        0.99
        >>> by_prefix("MiniGrid-DoorKey-8x8-v0", 0.95, 0.99)
        Traceback (most recent call last):
        ...
        ValueError: stages_by_prefix:'MiniGrid-DoorKey-8x8-v0',0.95,...: takes an id (a string), ...
    """
    if not isinstance(name, str) or not isinstance(values, Mapping):
        raise ValueError(
            f"stages_by_prefix:{name!r},{values!r},...: takes an id (a string), a mapping of "
            "id prefixes to values, and a default. Fix: "
            "${stages_by_prefix:${task.env.env_id},{Prefix-: value},default}"
        )
    return next((value for prefix, value in values.items() if name.startswith(prefix)), default)


# options listed per config loader: Hydra resolves the help template in every compose (it
# merges its own help config over it), twice a run, and each listing builds a repository
_OPTIONS: weakref.WeakKeyDictionary[Any, dict[str, tuple[str, ...]]] = weakref.WeakKeyDictionary()


def config_group_options(group: str) -> list[str]:
    """The options of config group ``group`` in the running Hydra app, the schemas this module
    stores left out (``[]`` outside one, or for no such group), listed once per config loader."""
    hydra = GlobalHydra.instance()
    if not hydra.is_initialized():
        return []
    loader = hydra.config_loader()
    listed = _OPTIONS.setdefault(loader, {})
    if group not in listed:
        try:
            names = loader.get_group_options(group)
        except HydraException:
            names = []
        listed[group] = tuple(name for name in names if not name.endswith("_schema"))
    return list(listed[group])  # a copy: the caller's to change


def group_options(group: str) -> str:
    """``a|b|c``: :func:`config_group_options` for the help (the ``stages_options`` resolver);
    ``?`` outside a Hydra app."""
    return "|".join(config_group_options(group)) or "?"


__all__ = ["by_prefix", "config_group_options", "register_configs"]
