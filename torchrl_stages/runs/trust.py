"""What a run directory (untrusted data) may make the package do: which config keys a resumed
run may change, and what a loaded config may instantiate."""

from __future__ import annotations

import re
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config import targets
from torchrl_stages.config.env_checks import missing_keys
from torchrl_stages.config.expansion import leaves
from torchrl_stages.runs.layout import RunDirError

#: top-level keys a resumed run may change: they do not alter what the stages train to
RESUMABLE_CHANGES = (
    "resume",
    "overwrite",
    "progress",
    "eval",
    "objective",
    "checkpoint_every",
    "checkpoint_keep",
    "stage_store",  # a stage taken from there is the one training gives, bit for bit
    "init_from",
)


def config_differences(old: DictConfig, new: DictConfig, ignore: tuple[str, ...] = ()) -> list[str]:
    """Dotted keys whose resolved values differ (``ignore``: key prefixes that may differ)."""
    flat_old, flat_new = (dict(leaves(OmegaConf.to_container(c, resolve=True))) for c in (old, new))
    return [
        k
        for k in sorted(flat_old.keys() | flat_new.keys())
        if flat_old.get(k, "<unset>") != flat_new.get(k, "<unset>")
        and not any(k == p or k.startswith(f"{p}.") for p in ignore)
    ]


#: root keys a config written by an earlier version lacks, with the value they had then
ADDED_KEYS: dict[str, Any] = {"all_stages": {}}


def _interpolations(node: Any, references: bool = False) -> Iterator[tuple[str, str]]:
    """``(dotted key, text)`` of every string under ``node`` holding ``${``; ``references``:
    but those that only refer to other keys or call the package's own ``stages_*`` resolvers
    (as Hydra writes ``.hydra/config.yaml``)."""
    for key, value in leaves(node):
        if not isinstance(value, str) or "${" not in value:
            continue
        resolvers = re.findall(r"\$\{\s*([^}:\s]+)\s*:", value)
        escaped = "\\$" in value  # unescaped when resolved: then read again
        if not references or escaped or any(not r.startswith("stages_") for r in resolvers):
            yield key, value


def shippedtargets(task_name: str) -> dict[str, str] | None:
    """``{dotted key: _target_}`` of the package's ``conf/task/<task_name>.yaml`` env and
    eval env; ``None`` for no such task, or one that leaves its env to the user (``???``)."""
    if not re.fullmatch(r"[A-Za-z0-9_]+", task_name):  # a file name under conf/task
        return None
    source = resources.files("torchrl_stages.conf").joinpath("task", f"{task_name}.yaml")
    if not source.is_file():
        return None
    shipped = yaml.safe_load(source.read_text()) or {}
    nodes = {key: shipped.get(key) or {} for key in ("env", "eval_env")}
    if missing_keys(OmegaConf.create(nodes), "task"):  # ??? : left to the user
        return None
    return dict(targets({"task": nodes}))


def check_trusted(cfg: DictConfig, source: Path) -> None:
    """Refuses a loaded config with any ``_target_`` (at any depth) other than its shipped
    task's at the same key; runs of your own env need ``trust=True``."""
    container = OmegaConf.to_container(cfg, resolve=False)
    task_name = str((container.get("task") or {}).get("name", ""))
    allowed = shippedtargets(task_name)
    fix = (
        "Fix: if you made this run (or checked what it imports), load it with trust=True "
        "(stages-eval --trust)"
    )
    if allowed is None:
        raise RunDirError(
            f"{source}: task '{task_name}' is not one the package ships with a fixed env, so "
            "loading it would import and call code that the run directory names (a run "
            f"directory is untrusted data). {fix}"
        )
    for key, target in targets(container):
        if allowed.get(key) != target:
            expected = f"'{allowed[key]}'" if key in allowed else "nothing there"
            raise RunDirError(
                f"{source}: {key}={target!r} is not what task '{task_name}' instantiates "
                f"({expected}); loading a run never runs code its files name. {fix}"
            )
