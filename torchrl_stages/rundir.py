"""A run directory on disk: its files, writing them safely, and reading them back.

A run directory holds ``config.yaml`` (the resolved config), ``stage_<k>.pt`` for every
finished stage, ``checkpoints/`` for the stage in progress, ``metrics.csv``, ``eval.json``,
figures, ``status.json`` when a run did not finish, and ``.stages/``: the run's record
(``run.json``: every entry the package wrote, the SHA-256 of the stage files and of
``config.yaml``, every launch's wall-clock) and the lock that keeps a second process out.

Files are written atomically (a temporary file unique to the process, then a rename); a
failed write leaves no temporary file. A run directory is untrusted data when it is read back:
checksums are verified, a config may only instantiate what its task ships with (see
:func:`check_trusted`), and a damaged or foreign file raises :class:`RunDirError` naming the
file and the fix.
"""

from __future__ import annotations

import io
import json
import logging
import re
import shutil
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, fields
from importlib import resources
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import TrainConfig, targets
from torchrl_stages.integrity import atomic_write, sha256_file
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runlock import LOCK_DIR, RunLock, RunLockedError
from torchrl_stages.schedules import get_schedule
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask
from torchrl_stages.tasks import EVAL_FILE
from torchrl_stages.validate import ConfigError, TargetError, missing_keys, validate_config

CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
STATUS_FILE = "status.json"
CHECKPOINTS = "checkpoints"
RECORD_FILE = "run.json"  # in .stages/
#: names of a run's files: a directory holding any of them (or a stage file) holds a run
RUN_MARKERS = (CONFIG_FILE, EVAL_FILE, METRICS_FILE, CHECKPOINTS)
#: what runs of versions without a record wrote (adopted when such a run is resumed)
LEGACY_ENTRIES = (*RUN_MARKERS, STATUS_FILE, "csv", ".hydra")
LEGACY_PATTERNS = ("stage_*.pt",)
#: the figures earlier versions wrote (the shipped tasks' reports and the learning curves)
LEGACY_FIGURES = (
    "learning_curves.png",
    "trajectories.png",
    "value_map.png",
    "value_map.npy",
    "manipulator.png",
    "cargo.png",
)
RECORD_FORMAT = "torchrl-stages run"

log = logging.getLogger("torchrl_stages")


class RunDirError(RuntimeError):
    """A run directory cannot be used as asked: it already holds a run, another process holds
    it, a file in it is damaged or foreign, or its config names code it may not run."""


def _flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _flatten(item, f"{prefix}{key}.")
    else:
        yield prefix.rstrip("."), value


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


#: root keys a config written by an earlier version lacks, with the value they had then
ADDED_KEYS: dict[str, Any] = {"all_stages": {}}


# ---------------------------------------------------------------------- what a config may run
_TASK_NAME = re.compile(r"^[A-Za-z0-9_]+$")


def _interpolations(node: Any, prefix: str = "") -> Iterator[tuple[str, str]]:
    """``(dotted key, text)`` of every string under ``node`` that holds ``${``."""
    if isinstance(node, dict):
        for key, item in node.items():
            yield from _interpolations(item, f"{prefix}.{key}" if prefix else str(key))
    elif isinstance(node, list):
        for index, item in enumerate(node):
            yield from _interpolations(item, f"{prefix}.{index}")
    elif isinstance(node, str) and "${" in node:
        yield prefix, node


def shippedtargets(task_name: str) -> dict[str, str] | None:
    """What the package's own ``conf/task/<task_name>.yaml`` instantiates (its env and
    whole-task eval env, ``{dotted key: _target_}``), or ``None`` when that is not fixed by
    the package: no such task, or a task that leaves its env to the user (``???``)."""
    if not _TASK_NAME.match(task_name):
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
    """Refuses a loaded config that would instantiate anything its task does not ship with.

    Every ``_target_`` of the config (at any depth, env keyword arguments included) must be
    one of the package's own task config (:func:`shipped_targets`), at the same key. Runs of
    your own env (``task=gym``, ``task=custom``, a config directory of yours) name code of
    yours to import: loading them needs ``trust=True``.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"task": {"name": "gridworld", "env": {
        ...     "_target_": "torchrl_stages.envs.GridWorldEnv", "size": 25}}})
        >>> check_trusted(cfg, Path("run/config.yaml"))
        >>> cfg.task.env.size = {"_target_": "os.system", "_args_": ["echo hi"]}
        >>> check_trusted(cfg, Path("run/config.yaml"))
        Traceback (most recent call last):
        ...
        torchrl_stages.rundir.RunDirError: run/config.yaml: task.env.size._target_='os.system' ...
    """
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


# ---------------------------------------------------------------------- the directory
class RunDir:
    """The files of one run directory and its record.

    Examples:
        >>> import tempfile
        >>> run = RunDir(tempfile.mkdtemp())
        >>> run.holds_run(), run.stage_file(3).name
        (False, 'stage_3.pt')
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._record: dict[str, Any] | None = None
        self._launch_start: float | None = None

    def stage_file(self, stage: int) -> Path:
        return self.path / f"stage_{stage}.pt"

    @property
    def config_file(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def record_file(self) -> Path:
        return self.path / LOCK_DIR / RECORD_FILE

    def holds_run(self) -> bool:
        """Whether a run was started here (a config, a stage, checkpoints, metrics or eval)."""
        return any((self.path / n).exists() for n in RUN_MARKERS) or any(
            self.path.glob("stage_*.pt")
        )

    def lock(self) -> RunLock:
        """Takes this directory's lock (one process at a time); :class:`RunDirError` names the
        process that holds it. The directory's other entries are checked for links once the
        lock is held: the process that holds it may be writing and deleting them meanwhile."""
        lock_dir = self.path / LOCK_DIR
        self._refuse_links([lock_dir, lock_dir / "lock"])
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            held = RunLock(self.path).acquire()
        except RunLockedError as err:
            raise RunDirError(str(err)) from None
        try:
            self.check_no_links()
        except BaseException:
            held.release(remove=held.created_dir)
            raise
        return held

    # ------------------------------------------------------------------ the record
    def has_record(self) -> bool:
        return self.record_file.is_file()

    @property
    def record(self) -> dict[str, Any]:
        """``.stages/run.json``: ``entries`` (what the package wrote here, with checksums),
        ``launches`` and ``phases`` (a joint run's). A missing one reads as empty."""
        if self._record is None:
            self._record = self._read_record()
        return self._record

    def _read_record(self) -> dict[str, Any]:
        empty = {"format": RECORD_FORMAT, "version": 1, "entries": {}, "launches": []}
        if not self.has_record():
            return empty
        try:
            record = json.loads(self.record_file.read_text())
            if record.get("format") != RECORD_FORMAT or not isinstance(record["entries"], dict):
                raise ValueError("not a run record")
            launches = record.get("launches", [])
            if not isinstance(launches, list) or not all(
                isinstance(x, dict) and isinstance(x.get("seconds", 0.0), int | float)
                for x in launches
            ):
                raise ValueError("launches is not a list of launches")
        except (OSError, ValueError, KeyError, AttributeError, UnicodeDecodeError) as err:
            raise RunDirError(
                f"{self.record_file} is damaged ({type(err).__name__}: {err}). Fix: restore it "
                "from a copy of the run, or retrain into a new directory"
            ) from err
        return {**empty, **record}

    def _save_record(self) -> None:
        (self.path / LOCK_DIR).mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.record, indent=1)
        atomic_write(self.record_file, lambda tmp: tmp.write_text(text))

    def claim(self, *names: str) -> None:
        """Records top-level entries as written by the package (before they are written:
        ``overwrite=true`` deletes exactly what is recorded)."""
        entries = self.record["entries"]
        new = [name for name in names if name not in entries]
        for name in new:
            entries[name] = {}
        if new or not self.has_record():
            self._save_record()

    def listing(self) -> set[str]:
        """The top-level entries of the directory now."""
        return {p.name for p in self.path.iterdir()} if self.path.is_dir() else set()

    def claim_new(self, before: set[str]) -> None:
        """Claims the top-level entries that appeared since the ``before`` listing (figures,
        a logger backend's directory), written while this process held the lock."""
        self.claim(*sorted(self.listing() - before - {LOCK_DIR}))

    def adopt_legacy(self) -> None:
        """Claims what a run written without a record holds (resuming such a run)."""
        names = [n for n in (*LEGACY_ENTRIES, *LEGACY_FIGURES) if (self.path / n).exists()]
        names += [p.name for pattern in LEGACY_PATTERNS for p in self.path.glob(pattern)]
        self.claim(*sorted(names))

    def _write_verified(self, name: str, write: Callable[[Path], None]) -> Path:
        """Writes the top-level file ``name`` atomically with its checksum in the record."""
        path = self.path / name
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

        atomic_write(path, write_and_record)
        return path

    def _verify(self, name: str, fix: str) -> None:
        """Raises :class:`RunDirError` if ``name`` differs from the checksum recorded when it
        was written (files without a recorded checksum pass)."""
        try:
            entry = self._read_record()["entries"].get(name, {})
            expected = {entry.get("sha256"), entry.get("previous")} - {None}
        except AttributeError:
            expected = set()
        if expected and sha256_file(self.path / name) not in expected:
            raise RunDirError(
                f"{self.path / name} is damaged (its bytes differ from those written, by their "
                f"SHA-256 in {self.record_file}). Fix: {fix}"
            )

    # ------------------------------------------------------------------ launches
    def begin_launch(self) -> None:
        """Starts this process's entry in the record's ``launches``."""
        self._launch_start = time.perf_counter()
        started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        self.record["launches"].append({"started": started, "seconds": 0.0, "outcome": "running"})
        self._save_record()

    def update_launch(self, outcome: str | None = None) -> None:
        """Records this launch's wall-clock so far (and its outcome: ``done``,
        ``interrupted``, ``diverged``, ``failed``); a killed launch keeps its last update."""
        if self._launch_start is None:
            return
        launch = self.record["launches"][-1]
        launch["seconds"] = time.perf_counter() - self._launch_start
        if outcome is not None:
            launch["outcome"] = outcome
            self._launch_start = None
        self._save_record()

    def training_time(self) -> dict[str, Any]:
        """Every launch (start, seconds, outcome) and their summed ``seconds``."""
        launches = [dict(launch) for launch in self._read_record()["launches"]]
        seconds = sum(float(launch.get("seconds", 0.0)) for launch in launches)
        return {"seconds": seconds, "launches": launches}

    # ------------------------------------------------------------------ config
    def write_config(self, cfg: DictConfig) -> None:
        """Writes the resolved config; :func:`load_run` rebuilds everything from it."""
        self.path.mkdir(parents=True, exist_ok=True)
        self._write_verified(CONFIG_FILE, lambda tmp: OmegaConf.save(cfg, tmp, resolve=True))

    @property
    def config_source(self) -> Path:
        """The file the config is read from: ``config.yaml``, or ``.hydra/config.yaml`` (the
        composed config Hydra recorded) when it is missing."""
        hydra = self.path / ".hydra" / CONFIG_FILE
        return hydra if not self.config_file.is_file() and hydra.is_file() else self.config_file

    def read_config(self) -> DictConfig:
        """The run's config, resolved and checked against the schema (``.hydra/config.yaml``
        when ``config.yaml`` is missing); a damaged or incomplete one, or one that holds an
        interpolation (``${...}``: a saved config is resolved, and resolving untrusted text
        can build nodes), raises :class:`RunDirError`."""
        path = self.config_source
        fix = (
            "restore it from the run's .hydra/config.yaml (or a copy of the run), or retrain "
            "into a new directory"
        )
        if not path.is_file():
            raise RunDirError(
                f"{self.config_file} not found: {self.path} is not a torchrl-stages run "
                "directory (pass the directory that `stages-train` printed at the end)."
            )
        if path == self.config_file:
            self._verify(CONFIG_FILE, fix)
        else:
            log.warning("%s is missing: reading %s instead", self.config_file, path)
        try:
            loaded = OmegaConf.load(path)
            if not isinstance(loaded, DictConfig):
                raise ValueError("it is not a mapping")
            container = OmegaConf.to_container(loaded, resolve=True)
            interpolation = next(_interpolations(container), None)
            if interpolation is not None:
                raise ValueError(f"{interpolation[0]} holds an interpolation, {interpolation[1]!r}")
            cfg = OmegaConf.create({**ADDED_KEYS, **container})
            missing = [f.name for f in fields(TrainConfig) if f.name not in cfg]
            if missing:
                raise ValueError(f"it lacks {', '.join(missing)}")
            OmegaConf.merge(OmegaConf.structured(TrainConfig), cfg)  # keys and types
            if not isinstance(cfg.task.get("stages"), DictConfig) or not cfg.task.stages:
                raise ValueError("it has no task.stages")
        except (yaml.YAMLError, OmegaConfBaseException, ValueError, UnicodeDecodeError) as err:
            raise RunDirError(
                f"{path} is damaged (not a complete stages-train config: "
                f"{type(err).__name__}: {str(err).splitlines()[0]}). Fix: {fix}"
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
        """Writes ``stage_<k>.pt`` atomically with its checksum: weights (targets included),
        optimizers, exploration state, counters, the stage's result and ``log`` (the logger's
        file sizes when the stage ended, where a resumed run rewinds them to). Never a
        non-finite one."""
        learner.check_finite()
        state = {"stage": stage, "name": name, "algo": learner.algo, "result": asdict(result)}
        state["log"] = dict(log or {})
        buffer = io.BytesIO()  # written by Python's file IO: a failed write is an OSError
        torch.save({**state, **learner.checkpoint()}, buffer)
        return self._write_verified(
            self.stage_file(stage).name, lambda tmp: tmp.write_bytes(buffer.getbuffer())
        )

    def read_stage(self, stage: int, map_location: Any = "cpu") -> dict[str, Any] | None:
        """The content of ``stage_<k>.pt`` (``None`` if the stage has not finished), after
        checking its checksum, its content and the stage it records."""
        path = self.stage_file(stage)
        if not path.is_file():
            return None
        fix = (
            f"delete it and rerun the same stages-train command with hydra.run.dir={self.path} "
            f"resume=true to retrain stage {stage}"
        )
        self._verify(path.name, fix)
        try:
            state = torch.load(path, map_location=map_location, weights_only=True)
            if not isinstance(state, dict) or not isinstance(state.get("model"), dict):
                raise ValueError("it holds no stage checkpoint")
            if not isinstance(state.get("result"), dict) or not isinstance(state.get("log"), dict):
                raise ValueError("it holds no stage result")
        except Exception as err:  # noqa: BLE001 - any failure to read it means it is damaged
            raise RunDirError(
                f"{path} is damaged (truncated or not a stage checkpoint: {type(err).__name__}). "
                f"Fix: {fix}"
            ) from err
        if state.get("stage") != stage:
            raise RunDirError(
                f"{path} holds stage {state.get('stage')!r}, not stage {stage} (renamed or "
                f"copied from elsewhere). Fix: {fix}"
            )
        return state

    def checkpoints(self, stage: int | str, every: int, keep: int) -> StageCheckpoints:
        """The periodic checkpoints of stage ``stage`` in progress (``"joint"``: of the joint
        schedule, all stages at once); each one written updates this launch's wall-clock."""
        self.claim(CHECKPOINTS)
        name = stage if isinstance(stage, str) else f"stage_{stage}"
        return StageCheckpoints(
            self.path / CHECKPOINTS / name, every, keep, on_save=lambda _: self.update_launch()
        )

    def clear_checkpoints(self, stage: int | str) -> None:
        """Drops stage ``stage``'s checkpoints (once ``stage_<k>.pt`` is written, or when a
        resumed run changed the stage's config)."""
        self.check_no_links()
        self.checkpoints(stage, 0, 1).clear()
        root = self.path / CHECKPOINTS
        if root.is_dir() and not any(root.iterdir()):
            root.rmdir()

    def check_no_links(self) -> None:
        """Raises :class:`RunDirError` if an entry the package reads or writes here is a
        symbolic link (it would read or write, or delete, what the link points to)."""
        entries = [self.path / n for n in (*LEGACY_ENTRIES, LOCK_DIR)]
        entries += [*self.path.glob("stage_*.pt"), *self.path.glob("*.png")]
        entries.append(self.path / "value_map.npy")
        for entry in entries:
            inner = entry.rglob("*") if entry.is_dir() and not entry.is_symlink() else []
            self._refuse_links([entry, *inner])

    @staticmethod
    def _refuse_links(paths: list[Path]) -> None:
        refuse_links(paths)

    def write_hydra_files(self, files: dict[str, Any]) -> None:
        """``.hydra/<name>`` for each ``{name: config}`` (what ``stages-train`` records of
        Hydra: the composed config, Hydra's config, the command-line overrides)."""
        self.claim(".hydra")
        out = self.path / ".hydra"
        out.mkdir(parents=True, exist_ok=True)
        for name, node in files.items():
            atomic_write(out / name, lambda tmp, node=node: OmegaConf.save(node, tmp))

    # ------------------------------------------------------------------ status, eval
    def write_status(self, status: str, reason: str | None = None, **extra: Any) -> None:
        """``status.json``: how the run ended when it did not finish (``failed``,
        ``diverged``, ``interrupted`` with its ``signal``, ...) and why."""
        self.path.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"status": status, "reason": reason, **extra}, indent=2)
        self.claim(STATUS_FILE)
        atomic_write(self.path / STATUS_FILE, lambda tmp: tmp.write_text(text))

    def read_eval(self) -> dict[str, Any] | None:
        """``eval.json`` if it is a readable JSON object, else ``None``."""
        try:
            data = json.loads((self.path / EVAL_FILE).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return None
        return data if isinstance(data, dict) else None

    def check_clearable(self) -> None:
        """Raises :class:`RunDirError` unless :meth:`clear` would remove every file of the run:
        a directory holding a run's files but no record, or files its record does not list,
        is refused and nothing in it is deleted."""
        if not self.has_record():
            found = sorted(n for n in [*RUN_MARKERS, STATUS_FILE] if (self.path / n).exists())
            found += sorted(p.name for p in self.path.glob("stage_*.pt"))
            raise RunDirError(
                f"overwrite=true: {self.path} holds {', '.join(found)} but no "
                f"{LOCK_DIR}/{RECORD_FILE}, the record of what torchrl-stages wrote there, so "
                "nothing in it is deleted. Fix: delete those files yourself, or pick another "
                "hydra.run.dir"
            )
        entries = self.record["entries"]
        foreign = [n for n in RUN_MARKERS if (self.path / n).exists() and n not in entries]
        foreign += [p.name for p in self.path.glob("stage_*.pt") if p.name not in entries]
        if foreign:
            raise RunDirError(
                f"overwrite=true: {self.path} holds {', '.join(sorted(foreign))}, which its "
                f"record ({LOCK_DIR}/{RECORD_FILE}) does not list as written by torchrl-stages, "
                "so nothing in it is deleted. Fix: delete those files yourself, or pick another "
                "hydra.run.dir"
            )

    def clear(self) -> list[str]:
        """Removes a previous run (``overwrite=true``): exactly the entries its record lists,
        nothing else; returns them (see :meth:`check_clearable`)."""
        self.check_clearable()
        entries = self.record["entries"]
        removed = []
        for name in sorted(entries):
            entry = self.path / name
            if "/" in name or name in ("", ".", "..", LOCK_DIR):
                continue  # a record lists top-level names only
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            elif entry.exists() or entry.is_symlink():
                entry.unlink()
            else:
                continue
            removed.append(name)
        self.record.update(entries={}, launches=[])
        self.record.pop("phases", None)
        self._save_record()
        return removed


@dataclass
class LoadedRun:
    """A finished run read back from disk (learners and results in stage order)."""

    cfg: DictConfig
    task: StagedTask
    learners: list[Learner]
    results: list[dict[str, Any]]


def load_stage(
    run: RunDir,
    task: StagedTask,
    stage: int,
    device: str | torch.device = "cpu",
    *,
    name: str | None = None,
) -> tuple[Learner, dict[str, Any]] | None:
    """Stage ``stage``'s learner and result from ``stage_<k>.pt`` (``None``: not finished),
    which must hold the stage ``name`` (default: the task's name of stage ``stage``)."""
    state = run.read_stage(stage, map_location=device)
    if state is None:
        return None
    name = task.stage_names[stage] if name is None else name
    if state.get("name") != name:
        raise RunDirError(
            f"{run.stage_file(stage)} holds stage {state.get('name')!r}, but the run's stage "
            f"{stage} is {name!r}. Fix: restore the config it was trained "
            "with, or delete the file and resume the run to retrain the stage."
        )
    fix = (
        "restore the config it was trained with, or delete the file and resume the run to "
        "retrain the stage."
    )
    learner = restore_learner(task, stage, state, device, run.stage_file(stage), fix)
    return learner, state["result"]


def restore_learner(
    task: StagedTask,
    stage: int,
    state: dict[str, Any],
    device: str | torch.device,
    source: Path,
    fix: str,
) -> Learner:
    """Stage ``stage``'s learner, built from the task's config and loaded from ``state`` (a
    stage file's content, read from ``source``); :class:`RunDirError` naming ``source`` and
    ``fix`` when they do not match."""
    learner = make_learner(task.stage_cfg(stage), task.specs(stage), device=device)
    try:
        learner.load_checkpoint(state)
        StageResult(**state["result"])
    except (KeyError, RuntimeError, ValueError, TypeError) as err:
        raise RunDirError(
            f"{source} does not match the run's config ({type(err).__name__}: "
            f"{str(err).splitlines()[0][:200]}). Fix: {fix}"
        ) from err
    return learner


def read_run_config(run: RunDir, device: str | torch.device, trust: bool) -> DictConfig:
    """The run's config, checked: what it may instantiate (unless ``trust``) and every value
    (as ``stages-train`` checks them), for loading on ``device``."""
    cfg = run.read_config()
    source = run.config_source
    if not trust:
        check_trusted(cfg, source)
    try:
        checked = cfg.copy()  # as it would run here: on this device, with no logger
        checked.device, checked.logger.backend = str(device), "none"
        validate_config(checked)
    except TargetError as err:  # code of the run's own that is not importable here
        raise RunDirError(f"{source}: {err}") from None
    except (ConfigError, OmegaConfBaseException, AttributeError, TypeError, ValueError) as err:
        raise RunDirError(
            f"{source} is not a valid config ({str(err).splitlines()[0]}). Fix: restore it "
            "from the run's .hydra/config.yaml, or retrain into a new directory"
        ) from err
    return cfg


def load_run(
    run_dir: str | Path, device: str | torch.device = "cpu", *, trust: bool = False
) -> LoadedRun:
    """Config, task, trained learners and training results of a finished run directory.

    The directory is untrusted data: its config may only instantiate what its task ships with
    (:func:`check_trusted`; ``trust=True`` lifts that, for runs of your own env), checksums are
    verified and nothing in it is unpickled.

    Examples:
        >>> from torchrl_stages import load_run  # doctest: +SKIP
        >>> run = load_run("outputs/2026-11-21/16-00-00")  # doctest: +SKIP
        >>> run.learners[0].policy, run.task.task_env(8)  # doctest: +SKIP
    """
    run = RunDir(run_dir)
    cfg = read_run_config(run, device, trust)
    try:
        task = StagedTask(cfg.task, device=device)
    except Exception as err:  # noqa: BLE001 - the run's env cannot be built here
        raise RunDirError(
            f"{run.path}: cannot build the env of task '{cfg.task.name}' "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}). Fix: "
            "install what the run's env needs (see its config.yaml task.env)"
        ) from err
    schedule = get_schedule(str(cfg.schedule.name))  # which file holds each stage's learner
    loaded: dict[int, tuple[Learner, dict[str, Any]] | None] = {}
    for k in range(task.num_stages):
        stored = schedule.stored_stage(k)
        if stored not in loaded:
            name = schedule.stage_name(task, stored)
            loaded[stored] = load_stage(run, task, stored, device, name=name)
    stages = [loaded[schedule.stored_stage(k)] for k in range(task.num_stages)]
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
    """The greedy stacked policy of a finished run (``trust``: see :func:`load_run`).

    It acts on the task env's TensorDicts as they come: an input without a ``"stage"`` entry
    gets its stage from the task's stage function (:class:`StackedPolicy`'s ``stage_fn``; the
    tasks without one, whose envs track their stage, write that entry themselves).

    Examples:
        >>> from torchrl_stages import load_policy  # doctest: +SKIP
        >>> policy = load_policy("outputs/2026-11-21/16-00-00")  # doctest: +SKIP
        >>> GridWorldEnv(batch_size=(8,)).rollout(200, policy)  # doctest: +SKIP
    """
    return run_policy(load_run(run_dir, device, trust=trust))


def run_policy(run: LoadedRun) -> StackedPolicy:
    """The greedy stacked policy of a loaded run, with its task's stage function."""
    stage_fn = getattr(run.task.spec_env, "stage_fn", None)
    return StackedPolicy([learner.policy for learner in run.learners], stage_fn=stage_fn)


def refuse_links(paths: Iterable[Path]) -> None:
    """Raises :class:`RunDirError` naming the first of ``paths`` that is a symbolic link (a
    run's own files are never links: writing or deleting through one touches another place)."""
    for path in paths:
        if path.is_symlink():
            raise RunDirError(
                f"{path} is a symbolic link: a run directory's own files are never "
                "links (writing or deleting through it would touch another place). "
                "Fix: replace it with the file itself, or pick another directory"
            )


__all__ = [
    "LoadedRun",
    "RunDir",
    "RunDirError",
    "check_trusted",
    "load_policy",
    "load_run",
    "refuse_links",
    "run_policy",
]
