"""Finished stages shared by runs (``stage_store=DIR``), and the stages a backward run takes
from there or from ``init_from=RUN_DIR`` instead of training."""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from torchrl_stages.config import ConfigError
from torchrl_stages.integrity import DamagedFileError, verify_checksums, write_checksums
from torchrl_stages.learners import Learner
from torchrl_stages.preemption import stop_if_asked
from torchrl_stages.runs.directory import RunDir, read_stage_file, stage_state, write_stage_file
from torchrl_stages.runs.identity import digest, stage_identities, stage_identity_inputs
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.loading import restore_learner
from torchrl_stages.runs.lock import RunLock, RunLockedError
from torchrl_stages.runs.trust import RESUMABLE_CHANGES, config_differences
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask

log = logging.getLogger("torchrl_stages")

ENTRIES, LOCKS, TMP = "entries", "locks", "tmp"
STAGE_FILE, ENTRY_FILE = "stage.pt", "entry.json"
ENTRY_FORMAT = "torchrl-stages stage"
POLL_S = 0.5  # seconds between two looks at a stage another job is training

#: a stage taken instead of trained: its learner, its result, and where it came from
Reused = tuple[Learner, StageResult, str]


class StoreError(ConfigError):
    """A stage store or an ``init_from`` run that cannot be used (found before training)."""


@dataclass
class StageEntry:
    """One stored stage, as ``stages-store ls`` lists it (``damaged``: why it is not served)."""

    identity: str
    path: Path
    last_used: float
    size: int
    damaged: str | None = None
    task: str = "?"
    stage: int = -1
    name: str = "?"
    algo: str = "?"
    seed: int = -1
    frames: int = 0
    success_rate: float | None = None
    created: str = "?"
    trained_in: str = "?"


#: what ``entry.json`` holds beyond its format and identity, as :class:`StageEntry` lists it
ENTRY_META = tuple(f.name for f in fields(StageEntry))[5:]


class SharedStageStore:
    """Finished stages, one entry per identity, shared by a sweep's jobs: each written whole in
    ``tmp/``, then renamed into ``entries/``, by the job holding ``locks/<identity>``.

    Examples:
        >>> import tempfile
        >>> store = SharedStageStore(tempfile.mkdtemp())
        >>> store.entries(), store.get("0" * 32) is None
        ([], True)
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        try:
            for sub in (ENTRIES, LOCKS, TMP):
                (self.root / sub).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StoreError(
                f"stage_store={self.root}: cannot create it ({err.strerror or err}). Fix: pick "
                "a writable directory, or drop stage_store"
            ) from err

    def path(self, identity: str) -> Path:
        return self.root / ENTRIES / identity

    def get(self, identity: str, map_location: Any = "cpu") -> dict[str, Any] | None:
        """``stage.pt`` of entry ``identity``, if any; a damaged entry is removed."""
        entry = self.path(identity)
        if not os.path.lexists(entry):
            return None
        try:
            state, _ = self._read(entry, identity, map_location)
        except DamagedFileError as err:
            why = f"{entry} is damaged ({err.reason})"
            log.warning(f"stage store: entry {why}; removed, the stage is trained again")
            self._discard(entry)
            return None
        with contextlib.suppress(OSError):  # a read-only store still serves
            os.utime(entry / ENTRY_FILE)  # when it was last used, for `stages-store prune`
        return state

    def _read(self, entry: Path, identity: str, map_location: Any = "cpu") -> tuple[dict, dict]:
        """The entry's stage file and ``entry.json``, verified."""
        if entry.is_symlink() or not entry.is_dir():
            raise DamagedFileError(entry, "not a directory written by the store")
        verify_checksums(entry, suffixes=(".pt", ".json"))
        try:
            meta = json.loads((entry / ENTRY_FILE).read_text())
            if not isinstance(meta, dict) or meta.get("format") != ENTRY_FORMAT:
                raise ValueError(f"not a {ENTRY_FORMAT} entry")
            if meta.get("identity") != identity:
                raise ValueError(f"it holds identity {meta.get('identity')!r}")
            state = read_stage_file(entry / STAGE_FILE, map_location, identity=identity)
        except Exception as err:  # noqa: BLE001 - unreadable in any way: damaged
            raise DamagedFileError(entry, f"{type(err).__name__}: {err}") from err
        return state, meta

    def put(self, identity: str, state: dict[str, Any], meta: dict[str, Any]) -> None:
        """Writes entry ``identity``; an entry that another job wrote first is kept."""
        entry = self.path(identity)
        tmp = self.root / TMP / f"{identity}.{uuid.uuid4().hex}"
        try:
            tmp.mkdir()
            write_stage_file(tmp / STAGE_FILE, {**state, "identity": identity})
            meta = {"format": ENTRY_FORMAT, "identity": identity, **meta}
            (tmp / ENTRY_FILE).write_text(json.dumps(meta, indent=1, default=str))
            write_checksums(tmp)
            try:
                os.rename(tmp, entry)
            except OSError:  # an entry is there: written by another job (or damaged)
                if self.get(identity) is None:  # damaged: removed, take its place
                    os.rename(tmp, entry)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def lock(self, identity: str) -> RunLock:
        return RunLock(self.root, file=self.root / LOCKS / identity)

    def _discard(self, entry: Path) -> None:
        """Renamed out of ``entries/`` first so no reader finds half of it."""
        gone = self.root / TMP / f"removed-{entry.name}-{uuid.uuid4().hex[:8]}"
        try:
            os.rename(entry, gone)
        except FileNotFoundError:
            return
        if gone.is_symlink():
            gone.unlink()
        else:
            shutil.rmtree(gone, ignore_errors=True)

    def entries(self) -> list[StageEntry]:
        out = []
        for entry in sorted((self.root / ENTRIES).iterdir()):
            damaged, meta = None, {}
            try:
                _, meta = self._read(entry, entry.name)
            except DamagedFileError as err:
                damaged = err.reason
            try:
                used = (entry / ENTRY_FILE).stat().st_mtime
            except OSError:
                used = entry.lstat().st_mtime
            known = {k: meta[k] for k in ENTRY_META if k in meta}
            size = sum(p.stat().st_size for p in entry.rglob("*") if p.is_file())
            out.append(StageEntry(entry.name, entry, used, size, damaged, **known))
        return sorted(out, key=lambda e: e.last_used)

    def remove(self, prefix: str) -> Path:
        found = [p for p in (self.root / ENTRIES).iterdir() if p.name.startswith(prefix)]
        if len(found) != 1:
            what = "no entry" if not found else f"{len(found)} entries"
            raise StoreError(
                f"{self.root}: {what} with an identity starting {prefix!r}. Fix: give more of "
                "the identity (stages-store ls lists them)"
            )
        self._discard(found[0])
        return found[0]

    def prune(self, older_than_s: float | None = None, dry_run: bool = False) -> list[Path]:
        """Removes damaged entries, those unused for ``older_than_s`` seconds, locks nobody
        holds and what interrupted writes left in ``tmp/``; returns them."""
        now, removed, held = time.time(), [], set()
        for entry in self.entries():
            stale = older_than_s is not None and now - entry.last_used > older_than_s
            if entry.damaged is not None or stale:
                removed.append(entry.path)
                if not dry_run:
                    self._discard(entry.path)
        for lock_file in (self.root / LOCKS).iterdir():
            try:
                self.lock(lock_file.name).acquire().release(remove=not dry_run)
                removed.append(lock_file)
            except RunLockedError:
                held.add(lock_file.name)  # a job trains that stage now
        for leftover in (self.root / TMP).iterdir():
            if leftover.name.split(".")[0] not in held:
                removed.append(leftover)
                if not dry_run:
                    shutil.rmtree(leftover, ignore_errors=True)
        return removed


class StageReuse:
    """The stages a backward run takes from ``init_from`` or the store instead of training;
    :meth:`take` returning ``None`` holds the stage's store lock until :meth:`trained`."""

    def __init__(self, cfg: DictConfig, run_dir: str | Path) -> None:
        self.inputs = stage_identity_inputs(cfg)
        self.identities = [digest(stage) for stage in self.inputs]
        self.cfg, self.run_dir = cfg, str(Path(run_dir).resolve())
        self.store = SharedStageStore(cfg.stage_store) if cfg.get("stage_store") else None
        self.init_run, self.init_identities = (
            self._open_init(cfg) if cfg.get("init_from") else (None, [])
        )
        self._held: dict[int, RunLock] = {}

    def _open_init(self, cfg: DictConfig) -> tuple[RunDir, list[str]]:
        path = Path(cfg.init_from)
        run = RunDir(path)
        if path.resolve() == Path(self.run_dir):
            raise StoreError(
                f"init_from={path}: that is this run's own directory. Fix: resume=true "
                "continues a run; init_from names another one"
            )
        if not run.config_file.is_file():
            raise StoreError(
                f"init_from={path}: no run there (no {run.config_file.name}). Fix: name a run "
                "directory written by stages-train"
            )
        try:
            saved = run.read_config()
            identities = stage_identities(saved)
        except (RunDirError, ValueError, TypeError, KeyError) as err:
            raise StoreError(f"init_from={path}: {err}") from err
        if identities and identities[-1] != self.identities[-1]:
            differ = config_differences(saved, cfg, ignore=(*RESUMABLE_CHANGES, "logger"))[:6]
            log.warning(
                f"init_from={path}: not even its last stage has this run's identity (the configs "
                f"differ in {', '.join(differ) or 'the library versions'}): every stage is trained"
            )
        return run, identities

    def take(self, task: StagedTask, stage: int, device: str) -> Reused | None:
        identity, init = self.identities[stage], self.init_run
        if init is not None and self.init_identities[stage : stage + 1] == [identity]:
            state = init.read_stage(stage, map_location=device)
            if state is not None:
                source = init.stage_file(stage)
                fix = f"retrain it: drop init_from, or delete {source}"
                restored = restore_learner(task, stage, state, device, source, fix)
                return *restored, f"init_from {init.path}"
        if self.store is None:
            return None
        found = self._from_store(task, stage, device)
        if found is not None:
            return found
        lock = self.store.lock(identity)
        for waited in itertools.count():
            try:
                lock.acquire()
                break
            except RunLockedError as err:
                if not waited:
                    where = f"stage {stage} ({task.stage_names[stage]}) of {self.store.root}"
                    log.info(f"{where}: waiting for {err.holder}, which trains it")
                stop_if_asked(f"waiting for stage {stage} in the stage store")
                time.sleep(POLL_S)
        found = self._from_store(task, stage, device)  # trained while this job waited
        if found is not None:
            lock.release()
            return found
        lock.announce()
        self._held[stage] = lock
        return None

    def _from_store(self, task: StagedTask, stage: int, device: str) -> Reused | None:
        identity = self.identities[stage]
        state = self.store.get(identity, map_location=device)
        if state is None:
            return None
        entry = self.store.path(identity)
        fix = f"stages-store rm {self.store.root} {identity[:12]}, then rerun"
        restored = restore_learner(task, stage, state, device, entry / STAGE_FILE, fix)
        return *restored, f"stage store {entry}"

    def trained(self, task: StagedTask, stage: int, learner: Learner, result: StageResult) -> None:
        if self.store is not None:
            meta = {
                "task": task.name,
                "stage": stage,
                "name": task.stage_names[stage],
                "algo": learner.algo,
                "seed": int(self.cfg.seed),
                "frames": result.frames,
                "success_rate": result.success_rate,
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "trained_in": self.run_dir,
                "inputs": self.inputs[stage],
            }
            state = stage_state(stage, learner, result)
            self.store.put(self.identities[stage], state, meta)
        lock = self._held.pop(stage, None)
        if lock is not None:  # a job waiting on the removed file takes a new one (RunLock)
            lock.release(remove=True)

    def close(self) -> None:
        for lock in self._held.values():
            lock.release()
        self._held.clear()
