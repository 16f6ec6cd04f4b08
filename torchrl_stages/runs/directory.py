"""A run directory on disk: its files written atomically with their checksums, and read back
as untrusted data (a damaged or foreign file raises :class:`RunDirError` naming the fix)."""

from __future__ import annotations

import io
import json
import logging
import os
import re
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, fields
from functools import cached_property
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import TrainConfig
from torchrl_stages.integrity import atomic_write, sha256_file
from torchrl_stages.learners import Learner
from torchrl_stages.runs.layout import (
    CHECKPOINTS,
    CONFIG_FILE,
    EVAL_FILE,
    LEGACY_ENTRIES,
    RECORD_FILE,
    RECORD_FORMAT,
    REPORT_FILES,
    RUN_MARKERS,
    STATUS_FILE,
    RunDirError,
)
from torchrl_stages.runs.lock import LOCK_DIR, RunLock
from torchrl_stages.runs.trust import ADDED_KEYS, _interpolations
from torchrl_stages.stage import StageResult

log = logging.getLogger("torchrl_stages")


def scope_checkpoints(
    root: Path, scope: int | str, cfg: DictConfig | None = None, on_save: Callable | None = None
) -> StageCheckpoints:
    """The checkpoints of ``scope`` (a stage or a group's name) at ``cfg``'s cadence (or none)."""
    name = scope if isinstance(scope, str) else f"stage_{scope}"
    every, keep = (0, 1) if cfg is None else (int(cfg.checkpoint_every), int(cfg.checkpoint_keep))
    return StageCheckpoints(root / name, every, keep, on_save=on_save)


def stage_state(stage: int, learner: Learner, result: StageResult, **extra: Any) -> dict[str, Any]:
    """What a stage file holds (never a non-finite learner)."""
    learner.check_finite()
    state = {"stage": stage, "algo": learner.algo, "result": asdict(result), **extra}
    return {**state, **learner.checkpoint()}


def write_stage_file(path: Path, state: dict[str, Any]) -> None:
    buffer = io.BytesIO()  # written by Python's file IO: a failed write is an OSError
    torch.save(state, buffer)
    path.write_bytes(buffer.getbuffer())


def read_stage_file(
    path: Path, map_location: Any, dicts: tuple[str, ...] = ("model", "result"), **expected: Any
) -> dict[str, Any]:
    """The stage file at ``path``; ValueError unless it holds ``dicts`` and ``expected``."""
    state = torch.load(path, map_location=map_location, weights_only=True)
    if not isinstance(state, dict) or not all(isinstance(state.get(k), dict) for k in dicts):
        raise ValueError(f"it holds no stage checkpoint with {', '.join(dicts)}")
    for key, value in expected.items():
        if state.get(key) != value:
            raise ValueError(f"it holds {key} {state.get(key)!r}, not {key} {value!r}")
    return state


def _damaged(path: Path, why: str, fix: str, err: Exception | None = None) -> RunDirError:
    """The error naming a damaged file, why (ending with ``err``'s first line) and the fix."""
    if err is not None:
        first_line = str(err).partition("\n")[0][:200]
        why += f"{type(err).__name__}: {first_line}"
    return RunDirError(f"{path} is damaged ({why}). Fix: {fix}")


def drop_checkpoints(root: Path, every: bool = False) -> None:
    """Removes ``root`` when empty; ``every``: its scopes' directories first."""
    if not root.is_dir():
        return
    for child in root.iterdir() if every else ():
        if child.is_dir() and re.fullmatch(r"\w+", child.name):
            shutil.rmtree(child)
    if not any(root.iterdir()):
        root.rmdir()


class RunDir:
    """The files of one run directory and its record (``.stages/run.json``).

    Examples:
        >>> import tempfile
        >>> run = RunDir(tempfile.mkdtemp())
        >>> run.holds_run(), run.stage_file(3).name
        (False, 'stage_3.pt')
    """

    def __init__(self, path: str | Path, launch: str | Path | None = None) -> None:
        self.path = Path(path)
        self.launch = Path(launch or path)  # the hydra.run.dir whose stages-train writes it
        self.config_file = self.path / CONFIG_FILE
        self.record_file = self.path / LOCK_DIR / RECORD_FILE
        self._launch_start: float | None = None

    def stage_file(self, stage: int) -> Path:
        return self.path / f"stage_{stage}.pt"

    def holds_run(self) -> bool:
        return bool(self._run_files())

    def _run_files(
        self, names: Iterable[str] = RUN_MARKERS, globs: Iterable[str] = ()
    ) -> list[str]:
        found = {n for n in names if (self.path / n).exists()}
        found |= {p.name for g in ("stage_*.pt", *globs) for p in self.path.glob(g)}
        return sorted(found)

    def lock(self) -> RunLock:
        """Takes this directory's lock; :class:`RunDirError` names the process holding it."""
        refuse_links([self.path / LOCK_DIR])
        self.path.mkdir(parents=True, exist_ok=True)
        held = RunLock(self.path).acquire()  # a RunLockedError is a RunDirError
        try:  # checked once the lock is held: its holder may be writing them meanwhile
            self.check_no_links()
        except BaseException:
            held.release(remove=held.created_dir)
            raise
        return held

    def has_record(self) -> bool:
        return self.record_file.is_file()

    @cached_property
    def record(self) -> dict[str, Any]:
        empty = _new_record()
        if not self.has_record():
            return empty
        try:
            record = json.loads(self.record_file.read_text())
            if record.get("format") != RECORD_FORMAT or not isinstance(record["entries"], dict):
                raise ValueError("not a run record")
            for launch in record.get("launches", []):  # a list of dicts, their seconds numbers
                float(launch.get("seconds", 0.0))
        except (OSError, ValueError, KeyError, AttributeError, TypeError) as err:
            fix = "restore it from a copy of the run, or retrain into a new directory"
            raise _damaged(self.record_file, "", fix, err) from err
        return {**empty, **record}

    def _save_record(self) -> None:
        (self.path / LOCK_DIR).mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.record, indent=1)
        atomic_write(self.record_file, lambda tmp: tmp.write_text(text))

    def claim(self, *names: str) -> None:
        """Records entries as the package's before they are written."""
        entries = self.record["entries"]
        new = {name: {} for name in names if name not in entries}
        entries.update(new)
        if new or not self.has_record():
            self._save_record()

    def listing(self) -> set[str]:
        return {p.name for p in self.path.iterdir()} if self.path.is_dir() else set()

    def claim_new(self, before: set[str]) -> None:
        self.claim(*sorted(self.listing() - before - {LOCK_DIR}))

    def adopt_legacy(self) -> None:
        self.claim(*self._run_files(LEGACY_ENTRIES, REPORT_FILES))

    def _write_verified(self, name: str, write: Callable[[Path], None]) -> None:
        self.claim(name)

        def write_and_record(tmp: Path) -> None:
            write(tmp)
            # the bytes on disk until the rename below: a kill in between leaves them valid
            previous = self.record["entries"].get(name, {}).get("sha256")
            entry = {"sha256": sha256_file(tmp)}
            if previous is not None and previous != entry["sha256"]:
                entry["previous"] = previous
            self.record["entries"][name] = entry
            self._save_record()

        atomic_write(self.path / name, write_and_record)

    def _verify(self, path: Path, fix: str) -> None:
        entry = self.record["entries"].get(path.relative_to(self.path).as_posix())
        if not isinstance(entry, dict):
            entry = {}
        expected = {entry.get("sha256"), entry.get("previous")} - {None}
        if expected and sha256_file(path) not in expected:
            why = f"its bytes differ from those written, by their SHA-256 in {self.record_file}"
            raise _damaged(path, why, fix)

    def begin_launch(self) -> None:
        self._launch_start = time.perf_counter()
        started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        self.record["launches"].append({"started": started, "seconds": 0.0, "outcome": "running"})
        self._save_record()

    def update_launch(self, outcome: str | None = None) -> None:
        """Records this launch's wall-clock so far, and its ``outcome`` when it ends."""
        if self._launch_start is None:
            return
        launch = self.record["launches"][-1]
        launch["seconds"] = time.perf_counter() - self._launch_start
        if outcome is not None:
            launch["outcome"] = outcome
            self._launch_start = None
        self._save_record()

    def training_time(self) -> dict[str, Any]:
        launches = [dict(launch) for launch in self.record["launches"]]
        seconds = sum(float(launch.get("seconds", 0.0)) for launch in launches)
        return {"seconds": seconds, "launches": launches}

    def write_config(self, cfg: DictConfig) -> None:
        self._write_verified(CONFIG_FILE, lambda tmp: OmegaConf.save(cfg, tmp, resolve=True))

    @property
    def config_source(self) -> Path:
        hydra = self.path / ".hydra" / CONFIG_FILE
        return hydra if not self.config_file.is_file() and hydra.is_file() else self.config_file

    def read_config(self) -> DictConfig:
        """The run's config, checked against the schema; interpolations (untrusted) refused."""
        path = self.config_source
        fix = "restore it from .hydra/config.yaml or a copy of the run, or retrain elsewhere"
        if not path.is_file():
            raise RunDirError(
                f"{self.config_file} not found: {self.path} is not a torchrl-stages run "
                "directory (pass the directory that `stages-train` printed at the end)."
            )
        self._verify(path, fix)  # .hydra/config.yaml has no checksum
        if path != self.config_file:
            log.warning("%s is missing: reading %s instead", self.config_file, path)
        try:
            loaded = OmegaConf.load(path)
            if not isinstance(loaded, DictConfig):
                raise ValueError("it is not a mapping")
            hydra = path != self.config_file  # as Hydra writes it: with references
            for key, text in _interpolations(OmegaConf.to_container(loaded), references=hydra):
                raise ValueError(f"{key} holds an interpolation, {text!r}")  # checked unresolved
            container = OmegaConf.to_container(loaded, resolve=True)
            cfg = OmegaConf.create({**ADDED_KEYS, **container})
            missing = [f.name for f in fields(TrainConfig) if f.name not in cfg]
            if missing:
                raise ValueError(f"it lacks {', '.join(missing)}")
            OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg)  # keys and types
            if not isinstance(cfg.task.get("stages"), DictConfig) or not cfg.task.stages:
                raise ValueError("it has no task.stages")
        except (yaml.YAMLError, OmegaConfBaseException, ValueError, UnicodeDecodeError) as err:
            raise _damaged(path, "not a complete stages-train config: ", fix, err) from err
        return cfg

    def save_stage(
        self, stage: int, name: str, learner: Learner, result: StageResult, log: dict[str, int]
    ) -> None:
        """Writes ``stage_<k>.pt``; ``log``: the logger's file sizes."""
        state = stage_state(stage, learner, result, name=name, log=dict(log))
        self._write_verified(self.stage_file(stage).name, lambda tmp: write_stage_file(tmp, state))

    def read_stage(self, stage: int, map_location: Any = "cpu") -> dict[str, Any] | None:
        path = self.stage_file(stage)
        if not path.is_file():
            return None
        fix = (
            f"delete it and rerun the same stages-train command with hydra.run.dir={self.launch} "
            f"resume=true to retrain stage {stage} and the stages trained after it"
        )
        self._verify(path, fix)
        try:
            return read_stage_file(path, map_location, ("model", "result", "log"), stage=stage)
        except Exception as err:  # noqa: BLE001 - any failure to read it means it is damaged
            raise _damaged(path, "truncated, or not this run's stage file: ", fix, err) from err

    def checkpoints(self, stage: int | str, cfg: DictConfig | None = None) -> StageCheckpoints:
        self.claim(CHECKPOINTS)
        root = self.path / CHECKPOINTS
        return scope_checkpoints(root, stage, cfg, lambda _: self.update_launch())

    def clear_checkpoints(self, stage: int | str) -> None:
        self.check_no_links()
        self.checkpoints(stage).clear()
        drop_checkpoints(self.path / CHECKPOINTS)

    def check_no_links(self) -> None:
        refuse_links([self.path / n for n in (*LEGACY_ENTRIES, LOCK_DIR)])
        refuse_links([p for g in ("stage_*.pt", *REPORT_FILES) for p in self.path.glob(g)])

    def write_hydra_files(self, files: dict[str, Any]) -> None:
        self.claim(".hydra")
        out = self.path / ".hydra"
        out.mkdir(parents=True, exist_ok=True)
        for name, node in files.items():
            atomic_write(out / name, lambda tmp, node=node: OmegaConf.save(node, tmp))

    def write_status(self, status: str, reason: str | None = None, **extra: Any) -> None:
        text = json.dumps({"status": status, "reason": reason, **extra}, indent=2)
        self.claim(STATUS_FILE)
        atomic_write(self.path / STATUS_FILE, lambda tmp: tmp.write_text(text))

    def read_eval(self) -> dict[str, Any] | None:
        try:
            data = json.loads((self.path / EVAL_FILE).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        return data if isinstance(data, dict) else None

    def check_clearable(self) -> None:
        record = f"{LOCK_DIR}/{RECORD_FILE}"
        if not self.has_record():
            found = ", ".join(self._run_files((*RUN_MARKERS, STATUS_FILE)))
            why = f"but no {record}, the record of what torchrl-stages wrote there"
        else:
            found = ", ".join(n for n in self._run_files() if n not in self.record["entries"])
            why = f"which its record ({record}) does not list as written by torchrl-stages"
        if found:
            raise RunDirError(
                f"overwrite=true: {self.path} holds {found}, {why}, so nothing in it is "
                "deleted. Fix: delete those files yourself, or pick another hydra.run.dir"
            )

    def clear(self) -> list[str]:
        """Removes exactly the entries the record lists (``overwrite=true``); returns them."""
        self.check_clearable()
        top = (n for n in self.record["entries"] if "/" not in n and n not in ("", ".", ".."))
        removed = sorted(n for n in top if n != LOCK_DIR and os.path.lexists(self.path / n))
        for entry in (self.path / name for name in removed):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        self.record.clear()  # what the launches kept (phases, reused stages) went with them
        self.record.update(_new_record())
        self._save_record()
        return removed


def _new_record() -> dict[str, Any]:
    return {"format": RECORD_FORMAT, "version": 1, "entries": {}, "launches": []}


def refuse_links(paths: Iterable[Path]) -> None:
    """Refuses a link among ``paths`` and what their directories hold (each entry seen once)."""
    for path in paths:
        if path.is_dir() and not path.is_symlink():
            with os.scandir(path) as entries:
                refuse_links([Path(entry.path) for entry in entries])
        elif path.is_symlink():
            raise RunDirError(
                f"{path} is a symbolic link: a run directory's own files are never "
                "links (writing or deleting through it would touch another place). "
                "Fix: replace it with the file itself, or pick another directory"
            )
