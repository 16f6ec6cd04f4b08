"""Per-stage learners: one module per algorithm, each registering itself in :data:`ALGORITHMS`;
a learner class of your own trains a stage through ``learner._target_``."""

import contextlib
import importlib
import pkgutil
from collections.abc import Mapping
from typing import Any

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config import ConfigError
from torchrl_stages.learners.base import ALGORITHMS, Learner, StageSpecs, register_algorithm
from torchrl_stages.learners.stacking import stacked_networks

for _module in pkgutil.iter_modules(__path__):  # each algorithm module registers itself
    importlib.import_module(f"{__name__}.{_module.name}")


def _field(cfg: Any, name: str) -> Any:
    """A key of a stage config, a mapping or a dataclass."""
    return cfg.get(name) if isinstance(cfg, Mapping) else getattr(cfg, name, None)


def learner_class(cfg: Any) -> type[Learner]:
    """The class ``cfg.learner._target_`` names, else the registered algorithm ``cfg.algo``.

    Examples:
        >>> learner_class({"algo": "dqn"}).algo
        'dqn'
        >>> learner_class({"algo": "dqn", "learner": {"_target_": "no_such.Learner"}})
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: learner._target_='no_such.Learner': ...
    """
    target = (_field(cfg, "learner") or {}).get("_target_")
    if target is None:
        name = _field(cfg, "algo")
        if name not in ALGORITHMS:
            raise ConfigError(
                f"algo={name!r}: unknown algorithm (known: {', '.join(ALGORITHMS)}). Fix: "
                f"select one with algo@task.stages.<stage>={'|'.join(ALGORITHMS)}"
            )
        return ALGORITHMS[name]
    try:
        cls = get_class(str(target))
    except Exception as err:  # noqa: BLE001 - Hydra wraps import errors in several types
        cause = err.__cause__ or err
        raise ConfigError(
            f"learner._target_={target!r}: cannot import it ({type(cause).__name__}: "
            f"{str(cause).splitlines()[0] if str(cause) else ''}). Fix: name a class of an "
            "importable module (pip install your package, or add its directory to PYTHONPATH)"
        ) from None
    if not (isinstance(cls, type) and issubclass(cls, Learner)):
        raise ConfigError(
            f"learner._target_={target!r}: is not a subclass of torchrl_stages.learners.Learner. "
            "Fix: subclass it (each module of torchrl_stages/learners/ is a whole example)"
        )
    return cls


def make_learner(
    cfg,
    specs: StageSpecs,
    compile: str = "off",
    device: str | torch.device | None = None,
    *,
    seeds: int | None = None,
) -> Learner:
    """The learner of stage config ``cfg`` (a ``learner`` node's other keys are its keyword
    arguments); ``compile``: the ``torch.compile`` mode of its losses; ``seeds``: that many
    seeds stacked in one learner (:mod:`.stacking`)."""
    cls = learner_class(cfg)
    if seeds is not None and not cls.stacks_seeds:
        stacked = ", ".join(n for n, c in ALGORITHMS.items() if c.stacks_seeds)
        raise ConfigError(
            f"algo={cls.algo}: cannot train several seeds in one process (it does not stack "
            f"its networks for seeds; those that do: {stacked}). Fix: train its seeds apart "
            "(stages-train -m seed=0,1,2) or pick one of those algorithms"
        )
    node = _field(cfg, "learner") or {}
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    kwargs = {k: v for k, v in node.items() if k != "_target_"}
    with torch.device(device) if device is not None else contextlib.nullcontext():
        with stacked_networks(seeds):
            return cls(cfg, specs, compile=compile, **kwargs)


__all__ = [
    "ALGORITHMS",
    "Learner",
    "StageSpecs",
    "learner_class",
    "make_learner",
    "register_algorithm",
]
