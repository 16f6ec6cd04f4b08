"""A finished run read back from its (untrusted) directory: config, task, learners, results."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.config import ConfigError, validate_config
from torchrl_stages.config.env_checks import TargetError
from torchrl_stages.learners import ALGORITHMS, Learner, learner_class, make_learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.trust import check_trusted
from torchrl_stages.schedules import get_schedule
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask


@dataclass
class LoadedRun:
    """A finished run read back from disk (learners and results in stage order)."""

    cfg: DictConfig
    task: StagedTask
    learners: list[Learner]
    results: list[dict[str, Any]]


def load_stage(
    run: RunDir, task: StagedTask, stage: int, device: str | torch.device, name: str
) -> tuple[Learner, dict[str, Any]] | None:
    """Stage ``stage``'s learner and result (``None``: not finished), if it holds ``name``."""
    state = run.read_stage(stage, map_location=device)
    if state is None:
        return None
    fix = (
        "restore the config it was trained with, or delete the file and resume the run to "
        "retrain the stage."
    )
    if state.get("name") != name:
        raise RunDirError(
            f"{run.stage_file(stage)} holds stage {state.get('name')!r}, but the run's stage "
            f"{stage} is {name!r}. Fix: {fix}"
        )
    learner, _ = restore_learner(task, stage, state, device, run.stage_file(stage), fix)
    return learner, state["result"]


def restore_learner(
    task: StagedTask, stage: int, state: dict, device: str | torch.device, source: Path, fix: str
) -> tuple[Learner, StageResult]:
    """Stage ``stage``'s learner loaded from ``state``, and its result; :class:`RunDirError`
    names ``source`` and ``fix`` when they do not fit the task's config."""
    learner = make_learner(task.stage_cfg(stage), task.specs(stage), device=device)
    try:
        learner.load_checkpoint(state)
        return learner, StageResult(**state["result"])
    except (KeyError, RuntimeError, ValueError, TypeError) as err:
        raise RunDirError(
            f"{source} does not match the run's config ({type(err).__name__}: "
            f"{str(err).splitlines()[0][:200]}). Fix: {fix}"
        ) from err


def load_run(
    run_dir: str | Path, device: str | torch.device = "cpu", *, trust: bool = False
) -> LoadedRun:
    """A finished run directory, read as untrusted data: checksums verified, nothing unpickled,
    and only what its task ships with instantiated unless ``trust=True``."""
    run = RunDir(run_dir)
    cfg, source = run.read_config(), run.config_source
    if not trust:
        check_trusted(cfg, source)
    try:  # checked as stages-train checks it, as it would run here: no logger
        schedule = get_schedule(str(cfg.schedule.name))
        checked = cfg.copy()
        checked.device, checked.logger.backend = str(device), "none"
        validate_config(checked, schedule, learner_class, ALGORITHMS)
    except TargetError as err:  # code of the run's own that is not importable here
        raise RunDirError(f"{source}: {err}") from None
    except (ConfigError, OmegaConfBaseException, AttributeError, TypeError, ValueError) as err:
        raise RunDirError(
            f"{source} is not a valid config ({str(err).splitlines()[0]}). Fix: restore it "
            "from the run's .hydra/config.yaml, or retrain into a new directory"
        ) from err
    try:
        task = StagedTask(cfg.task, device=device)
    except Exception as err:  # noqa: BLE001 - the run's env cannot be built here
        raise RunDirError(
            f"{run.path}: cannot build the env of task '{cfg.task.name}' "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}). Fix: "
            "install what the run's env needs (see its config.yaml task.env)"
        ) from err
    stored = [schedule.stored_stage(k) for k in range(task.num_stages)]
    loaded = {
        k: load_stage(run, task, k, device, schedule.stage_name(task, k))
        for k in dict.fromkeys(stored)
    }
    stages = [loaded[k] for k in stored]
    missing = [run.stage_file(k).name for k, s in enumerate(stages) if s is None]
    if missing:
        raise RunDirError(
            f"{run.path} lacks {', '.join(missing)}: those stages never finished training. "
            f"Fix: rerun the same stages-train command with hydra.run.dir={run.path} resume=true "
            "(stages are written from the last one backwards)."
        )
    return LoadedRun(cfg, task, [s[0] for s in stages], [s[1] for s in stages])


def load_policy(
    run_dir: str | Path, device: str | torch.device = "cpu", *, trust: bool = False
) -> StackedPolicy:
    return run_policy(load_run(run_dir, device, trust=trust))


def run_policy(run: LoadedRun) -> StackedPolicy:
    stage_fn = getattr(run.task.spec_env, "stage_fn", None)
    return StackedPolicy([learner.policy for learner in run.learners], stage_fn=stage_fn)
