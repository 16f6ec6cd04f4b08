"""The schemas in Hydra's ConfigStore, the resolvers ``conf/`` uses and Hydra's errors in one
line. ``task.stages``, each stage and ``task.env`` stay open (``validate_config`` checks their
keys), so that one form of a key works on every task."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Mapping
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.config.schema import LoggerConfig, ScheduleConfig, TrainConfig, TuneAppConfig


def register_configs(algorithms: Mapping[str, Any]) -> None:
    """Registers the root schemas, each learner's ``Config`` and the ``stages_*`` resolvers."""
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=_open(TrainConfig, "task.stages", "task.env"))
    cs.store(name="tune_schema", node=_open(TuneAppConfig, "task.stages", "task.env"))
    cs.store(group="logger", name="logger_schema", node=LoggerConfig)
    cs.store(group="schedule", name="schedule_schema", node=ScheduleConfig)
    for name, learner in algorithms.items():
        cs.store(group="algo", name=f"{name}_schema", node=_open(learner.Config, ""))
    register = functools.partial(OmegaConf.register_new_resolver, replace=True)
    register("stages_algorithms", lambda: "|".join(algorithms))
    register("stages_options", lambda group: "|".join(config_group_options(group)) or "?")
    register("stages_by_prefix", by_prefix)


def _open(schema: type, *keys: str) -> DictConfig:
    """``schema`` whose nodes at ``keys`` (``""``: the root) take keys they lack without ``+``."""
    node = OmegaConf.structured(schema)
    for key in keys:
        OmegaConf.set_struct(node if not key else OmegaConf.select(node, key), False)
    return node


def by_prefix(name: str, values: Mapping[str, Any], default: Any) -> Any:
    """The ``stages_by_prefix`` resolver: the value of the first key of ``values`` that
    ``name`` starts with, else ``default``.

    Examples:
        >>> by_prefix("MiniGrid-KeyCorridorS3R3-v0", {"MiniGrid-KeyCorridor": 0.95}, 0.99)
        0.95
    """
    if not isinstance(name, str) or not isinstance(values, Mapping):
        raise ValueError(
            f"stages_by_prefix:{name!r},{values!r},...: takes an id (a string), a mapping of "
            "id prefixes to values, and a default. Fix: "
            "${stages_by_prefix:${task.env.env_id},{Prefix-: value},default}"
        )
    return next((value for prefix, value in values.items() if name.startswith(prefix)), default)


def config_group_options(group: str) -> list[str]:
    """The options of config group ``group`` in the running Hydra app, schemas left out."""
    hydra = GlobalHydra.instance()
    return list(_options(hydra.config_loader(), group)) if hydra.is_initialized() else []


@functools.lru_cache(maxsize=64)  # Hydra resolves the help template twice a run
def _options(loader: Any, group: str) -> tuple[str, ...]:
    with contextlib.suppress(HydraException):
        return tuple(n for n in loader.get_group_options(group) if not n.endswith("_schema"))
    return ()


def hydra_message(err: BaseException) -> str:
    """Hydra's message (and its OmegaConf cause) on one line, without the search path."""
    text = str(err).split("Config search path")[0]
    if isinstance(err.__cause__, OmegaConfBaseException):
        text += "\n" + str(err.__cause__).splitlines()[0]
    parts: list[str] = []
    for raw in text.splitlines():
        line = raw.strip().rstrip(".")
        if raw.startswith("\t") and parts:  # one of a listing's entries
            parts[-1] += (" " if parts[-1].endswith(":") else ", ") + line
        elif line:
            parts.append(line)
    return "; ".join(parts) or type(err).__name__
