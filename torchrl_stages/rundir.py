"""A run directory on disk: its files, writing them safely, and reading them back.

A run directory holds ``config.yaml`` (the resolved config), ``stage_<k>.pt`` for every
finished stage, ``checkpoints/stage_<k>/`` for the stage in progress, ``metrics.csv``,
``eval.json``, figures, and ``status.json`` when a run failed. Files are written atomically
(a temporary file, then a rename); reading a damaged one raises :class:`RunDirError` naming the
file and the fix.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import zipfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

CONFIG_FILE = "config.yaml"
EVAL_FILE = "eval.json"
METRICS_FILE = "metrics.csv"
STATUS_FILE = "status.json"
CHECKPOINTS = "checkpoints"
# what a run writes besides figures (``overwrite=true`` removes these and the figures)
RUN_ENTRIES = (CONFIG_FILE, EVAL_FILE, METRICS_FILE, STATUS_FILE, CHECKPOINTS, "csv", ".hydra")
FIGURES = ("*.png", "value_map.npy")


class RunDirError(RuntimeError):
    """A run directory cannot be used as asked: it already holds a run, a file in it is
    damaged, or a resumed run's config differs from the one it was started with."""


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    write(tmp)
    os.replace(tmp, path)


def _flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _flatten(item, f"{prefix}{key}.")
    else:
        yield prefix.rstrip("."), value


def config_differences(old: DictConfig, new: DictConfig, ignore: tuple[str, ...] = ()) -> list[str]:
    """Dotted keys whose resolved values differ between two configs (``ignore``: key prefixes
    that may differ).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> a = OmegaConf.create({"seed": 0, "eval": {"plots": True}, "task": {"lr": 1.0}})
        >>> b = OmegaConf.create({"seed": 0, "eval": {"plots": False}, "task": {"lr": 2.0}})
        >>> config_differences(a, b, ignore=("eval",))
        ['task.lr']
    """
    flat_old = dict(_flatten(OmegaConf.to_container(old, resolve=True)))
    flat_new = dict(_flatten(OmegaConf.to_container(new, resolve=True)))
    keys = sorted(set(flat_old) | set(flat_new))
    return [
        k
        for k in keys
        if flat_old.get(k, "<unset>") != flat_new.get(k, "<unset>")
        and not any(k == p or k.startswith(f"{p}.") for p in ignore)
    ]


class RunDir:
    """The files of one run directory.

    Examples:
        >>> import tempfile
        >>> run = RunDir(tempfile.mkdtemp())
        >>> run.holds_run(), run.stage_file(3).name
        (False, 'stage_3.pt')
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def stage_file(self, stage: int) -> Path:
        return self.path / f"stage_{stage}.pt"

    @property
    def config_file(self) -> Path:
        return self.path / CONFIG_FILE

    def holds_run(self) -> bool:
        """Whether a run was started here (a config, a stage, checkpoints, metrics or eval)."""
        names = (CONFIG_FILE, EVAL_FILE, METRICS_FILE, CHECKPOINTS)
        return any((self.path / n).exists() for n in names) or any(self.path.glob("stage_*.pt"))

    # ------------------------------------------------------------------ config
    def write_config(self, cfg: DictConfig) -> None:
        """Writes the resolved config; :func:`load_run` rebuilds everything from it."""
        self.path.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.config_file, lambda tmp: OmegaConf.save(cfg, tmp, resolve=True))

    def read_config(self) -> DictConfig:
        """The run's resolved config; a missing or damaged file raises :class:`RunDirError`."""
        path = self.config_file
        if not path.is_file():
            raise RunDirError(
                f"{path} not found: {self.path} is not a torchrl-stages run directory (pass the "
                "directory that `stages-train` printed at the end)."
            )
        try:
            cfg = OmegaConf.load(path)
            if not isinstance(cfg, DictConfig) or "task" not in cfg or "stages" not in cfg.task:
                raise ValueError("it has no task.stages")
        except (yaml.YAMLError, OmegaConfBaseException, ValueError, UnicodeDecodeError) as err:
            raise RunDirError(
                f"{path} is damaged (not a complete stages-train config: "
                f"{type(err).__name__}: {str(err).splitlines()[0]}). Fix: restore it from the "
                f"run's .hydra/config.yaml, or retrain into a new directory."
            ) from err
        return cfg

    # ------------------------------------------------------------------ stages
    def save_stage(
        self,
        stage: int,
        name: str,
        learner: Learner,
        result: StageResult,
        log: dict[str, int] | None = None,
    ) -> Path:
        """Writes ``stage_<k>.pt`` atomically: weights (targets included), optimizers,
        exploration state, counters, the stage's result and ``log`` (the logger's file sizes
        when the stage ended, where a resumed run rewinds them to). Never a non-finite one."""
        learner.check_finite()
        path = self.stage_file(stage)
        state = {"stage": stage, "name": name, "algo": learner.algo, "result": asdict(result)}
        state["log"] = dict(log or {})
        _atomic_write(path, lambda tmp: torch.save({**state, **learner.checkpoint()}, tmp))
        return path

    def read_stage(self, stage: int, map_location: Any = "cpu") -> dict[str, Any] | None:
        """The content of ``stage_<k>.pt`` (``None`` if the stage has not finished)."""
        path = self.stage_file(stage)
        if not path.is_file():
            return None
        try:
            state = torch.load(path, map_location=map_location, weights_only=True)
            if not isinstance(state, dict) or "model" not in state:
                raise ValueError("it holds no stage checkpoint")
        except (
            pickle.UnpicklingError,
            RuntimeError,
            EOFError,
            ValueError,
            zipfile.BadZipFile,
            OSError,
        ) as err:
            raise RunDirError(
                f"{path} is damaged (truncated or not a stage checkpoint: {type(err).__name__}). "
                f"Fix: delete it and rerun the same stages-train command with "
                f"hydra.run.dir={self.path} resume=true to retrain stage {stage}."
            ) from err
        return state

    def checkpoints(self, stage: int | str, every: int, keep: int) -> StageCheckpoints:
        """The periodic checkpoints of stage ``stage`` in progress (``"joint"``: of the joint
        schedule, all stages at once)."""
        name = stage if isinstance(stage, str) else f"stage_{stage}"
        return StageCheckpoints(self.path / CHECKPOINTS / name, every, keep)

    def clear_checkpoints(self, stage: int | str) -> None:
        """Drops stage ``stage``'s checkpoints (once ``stage_<k>.pt`` is written)."""
        self.checkpoints(stage, 0, 1).clear()
        root = self.path / CHECKPOINTS
        if root.is_dir() and not any(root.iterdir()):
            root.rmdir()

    # ------------------------------------------------------------------ status
    def write_status(self, status: str, reason: str | None = None) -> None:
        """``status.json``: how the run ended (``failed`` / ``diverged`` with the reason)."""
        self.path.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"status": status, "reason": reason}, indent=2)
        _atomic_write(self.path / STATUS_FILE, lambda tmp: tmp.write_text(text))

    def clear(self) -> None:
        """Removes a previous run's files (``overwrite=true``); Hydra's log stays."""
        for name in RUN_ENTRIES:
            entry = self.path / name
            if entry.is_dir():
                shutil.rmtree(entry)
            elif entry.exists():
                entry.unlink()
        for pattern in ("stage_*.pt", *FIGURES):
            for entry in self.path.glob(pattern):
                entry.unlink()


@dataclass
class LoadedRun:
    """A finished run read back from disk (learners and results in stage order)."""

    cfg: DictConfig
    task: StagedTask
    learners: list[Learner]
    results: list[dict[str, Any]]


def load_stage(
    run: RunDir, task: StagedTask, stage: int, device: str | torch.device = "cpu"
) -> tuple[Learner, dict[str, Any]] | None:
    """Stage ``stage``'s learner and result from ``stage_<k>.pt`` (``None``: not finished)."""
    state = run.read_stage(stage, map_location=device)
    if state is None:
        return None
    learner = make_learner(task.stage_cfg(stage), task.specs(stage), device=device)
    try:
        learner.load_checkpoint(state)
    except (KeyError, RuntimeError, ValueError) as err:
        raise RunDirError(
            f"{run.stage_file(stage)} does not match the run's config.yaml ({type(err).__name__}: "
            f"{str(err).splitlines()[0][:200]}). Fix: restore the config it was trained with, or "
            "delete the file and resume the run to retrain the stage."
        ) from err
    return learner, state["result"]


def load_run(run_dir: str | Path, device: str | torch.device = "cpu") -> LoadedRun:
    """Config, task, trained learners and training results of a finished run directory.

    Examples:
        >>> from torchrl_stages import load_run  # doctest: +SKIP
        >>> run = load_run("outputs/2026-11-21/16-00-00")  # doctest: +SKIP
        >>> run.learners[0].policy, run.task.task_env(8)  # doctest: +SKIP
    """
    run = RunDir(run_dir)
    cfg = run.read_config()
    task = StagedTask(cfg.task, device=device)
    if cfg.get("schedule", {}).get("name") == "flat":  # one learner acts in every stage
        stages = [load_stage(run, task, 0, device)] * task.num_stages
    else:
        stages = [load_stage(run, task, k, device) for k in range(task.num_stages)]
    missing = [run.stage_file(k).name for k, s in enumerate(stages) if s is None]
    if missing:
        raise RunDirError(
            f"{run.path} lacks {', '.join(missing)}: those stages never finished training. "
            f"Fix: rerun the same stages-train command with hydra.run.dir={run.path} resume=true "
            "(stages are written from the last one backwards)."
        )
    return LoadedRun(cfg, task, [s[0] for s in stages], [s[1] for s in stages])


def load_policy(run_dir: str | Path, device: str | torch.device = "cpu") -> StackedPolicy:
    """The greedy stacked policy of a finished run.

    Examples:
        >>> from torchrl_stages import load_policy  # doctest: +SKIP
        >>> policy = load_policy("outputs/2026-11-21/16-00-00")  # doctest: +SKIP
        >>> env.rollout(200, policy)  # an env tagged by StageTransform  # doctest: +SKIP
    """
    run = load_run(run_dir, device)
    return StackedPolicy([learner.policy for learner in run.learners])
