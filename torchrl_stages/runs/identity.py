"""Stage identity: under the backward schedule, equal identities train to the same weights."""

from __future__ import annotations

import hashlib
import json
from importlib.metadata import version
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

#: bumped by any change of the package that alters the weights a stage config trains to, so
#: that stored stages written before it are never served after it
STAGE_SEMANTICS = 1


def stage_identity_inputs(cfg: DictConfig) -> list[dict[str, Any]]:
    """What determines each stage's weights, in stage order (``"next"``: the identity of the
    stage after it); logger, progress, checkpoint cadence and whole-task eval are left out."""
    task = cfg.task
    names = list(task.stages)
    common = {
        "semantics": STAGE_SEMANTICS,
        # a stage the joint schedule trained is not the one the backward schedule trains
        "schedule": OmegaConf.to_container(cfg.schedule, resolve=True),
        "versions": {
            "torch": torch.__version__,
            **{p: version(p) for p in ("torchrl", "tensordict")},
        },
        "env": OmegaConf.to_container(task.env, resolve=True),
        "stage_starts": bool(task.get("stage_starts", True)),
        "num_stages": len(names),
        "seed": int(cfg.seed),
        "device": torch.device(str(cfg.device)).type,
        "compile": str(cfg.get("compile", "auto")),
        "threads": int(cfg.threads),
    }
    inputs: list[dict[str, Any]] = []
    following = None
    for k in reversed(range(len(names))):
        config = OmegaConf.to_container(task.stages[names[k]], resolve=True)
        stage = {**common, "stage": k, "config": config, "next": following}
        if k == 0 and cfg.eval.get("probe", False):  # its evaluations run the whole task too
            stage["probe"] = True
        inputs.insert(0, stage)
        following = digest(stage)
    return inputs


def stage_identities(cfg: DictConfig) -> list[str]:
    return [digest(stage) for stage in stage_identity_inputs(cfg)]


def digest(inputs: dict[str, Any]) -> str:
    text = json.dumps(inputs, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]
