"""Periodic checkpoints of the stage in progress on ``torchrl.checkpoint``, as tensors and JSON
(never a pickle) with checksums; a damaged checkpoint is skipped for the one before."""

from __future__ import annotations

import dataclasses
import errno
import logging
import re
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from torch.utils._pytree import tree_leaves
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointRotation,
    GlobalRNGState,
    StateDictCheckpointAdapter,
)

from torchrl_stages.integrity import (
    DamagedFileError,
    ensure_free_space,
    verify_checksums,
    write_checksums,
)

PREFIX = "frames"
MANIFEST = "manifest.json"  # torchrl.checkpoint's own record of the components
PAYLOAD_SUFFIXES = (".json", ".memmap")

log = logging.getLogger("torchrl_stages")


@dataclasses.dataclass(eq=False)
class StateOf:
    """A pair of functions as ``state_dict`` / ``load_state_dict``.

    Examples:
        >>> box = {"n": 1}
        >>> state = StateOf(lambda: dict(box), box.update)
        >>> state.load_state_dict({"n": 2}); box["n"]
        2
    """

    state_dict: Callable[[], Any]
    load_state_dict: Callable[[Any], None] | None


class CheckpointDamagedError(RuntimeError):
    """A checkpoint on disk cannot be read back."""


#: the form of the loops' state in a checkpoint: a loop refuses one of another form
CHECKPOINT_FORMAT = 2


class CheckpointFormatError(ValueError):
    """A checkpoint written by a version whose loops kept another state."""


class SavedCounters:
    """A loop's counters (a dataclass with a ``format`` field) as a checkpoint component."""

    def state_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointFormatError(f"format {state.get('format', 1)}, not {CHECKPOINT_FORMAT}")
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            setattr(self, f.name, state[f.name])


class TensorStateAdapter(StateDictCheckpointAdapter):
    """torchrl's state-dict adapter in its tensor + JSON format, with checksums."""

    def __init__(self) -> None:
        super().__init__(payload_format="directory")

    def save(self, component: Any, path: Path, *, args: tuple, kwargs: Mapping) -> Any:
        state = component.state_dict(*args, **kwargs)
        nbytes = sum(t.nbytes for t in tree_leaves(state) if isinstance(t, torch.Tensor))
        ensure_free_space(path.parent, nbytes)
        try:
            super().save(StateOf(lambda: state, None), path, args=(), kwargs={})
        except RuntimeError as err:  # tensordict's memory-mapped writes report OS errors so
            raise OSError(errno.EIO, str(err).splitlines()[0], str(path)) from err
        except OSError as err:  # a JSON part's write names no file: the component's
            if err.filename is not None:
                raise
            raise OSError(err.errno, err.strerror or str(err), str(path)) from err
        write_checksums(path)
        return state


def verify_checkpoint(path: Path) -> None:
    """Raises :class:`DamagedFileError` unless each file is the manifest or a verified payload."""
    try:
        components = Checkpoint.manifest(path)["components"]
        dirs = {path / record["path"] for record in components.values()}
    except (CheckpointError, OSError, KeyError, TypeError, ValueError) as err:
        raise DamagedFileError(path / MANIFEST, f"unreadable ({type(err).__name__})") from err
    for file in path.rglob("*"):
        if file.is_dir() and not file.is_symlink():
            continue
        if file != path / MANIFEST and not any(d in file.parents for d in dirs):
            raise DamagedFileError(file, "a file that was never written there")
    for directory in dirs:  # torchrl's manifest has refused absolute and ".." paths
        if path not in directory.parents:
            raise DamagedFileError(path / MANIFEST, "a component outside the checkpoint")
        verify_checksums(directory, PAYLOAD_SUFFIXES)


class StageCheckpoints:
    """The ``keep`` newest checkpoints of one stage in ``directory``, one per ``every`` frames
    (``0``: only when asked, e.g. on a signal); ``on_save`` sees each one written.

    Examples:
        >>> import tempfile, torch
        >>> ckpts = StageCheckpoints(tempfile.mkdtemp(), every=100)
        >>> components = {"net": torch.nn.Linear(2, 1), "counters": {"frames": 100}}
        >>> ckpts.due(99), ckpts.due(100)
        (False, True)
        >>> path = ckpts.save(100, components)
        >>> ckpts.load(ckpts.latest(), components) == path
        True
    """

    def __init__(
        self, directory: str | Path, every: int, keep: int = 2, on_save: Callable | None = None
    ) -> None:
        self.directory = Path(directory)
        self.every, self.keep = int(every), int(keep)
        self.on_save = on_save
        self._next = self.every
        self._verified: Path | None = None
        self._damaged: dict[Path, DamagedFileError] = {}  # each reported once

    def due(self, frames: int) -> bool:
        return self.every > 0 and frames >= self._next

    def _after(self, frames: int) -> None:
        self._next = (frames // self.every + 1) * self.every if self.every > 0 else 0

    def _checkpoint(self, components: Mapping[str, Any]) -> Checkpoint:
        ckpt = Checkpoint(format="directory")
        adapter = TensorStateAdapter()
        for name, component in {**components, "rng": GlobalRNGState()}.items():
            if not hasattr(component, "state_dict"):  # a plain dict (counters)
                component = StateOf(lambda c=component: dict(c), component.update)
            ckpt.register(name, component, adapter=adapter)
        return ckpt

    def save(self, frames: int, components: Mapping[str, Any]) -> Path:
        rotation = CheckpointRotation(self.directory, keep_last=self.keep, prefix=PREFIX)
        path = rotation.save(self._checkpoint(components), step=int(frames))
        self._after(frames)
        self._verified = path
        if self.on_save is not None:
            self.on_save(path)
        return path

    def latest(self, components: Mapping[str, Any] | None = None) -> Path | None:
        """The newest whole checkpoint, if any (damaged ones skipped, each with one warning);
        with ``components``: the newest that loads back into them (one that does not is
        skipped as a damaged one is), loaded."""
        found = self.directory.iterdir() if self.directory.is_dir() else ()
        # every entry of the rotation's form, readable or not
        candidates = [p for p in found if re.fullmatch(rf"{PREFIX}-\d+", p.name)]
        candidates.sort(key=_frames, reverse=True)
        for i, path in enumerate(candidates):  # each newer one is damaged
            if path in self._damaged:
                continue
            try:
                if path != self._verified:
                    verify_checkpoint(path)
                    if i:
                        log.warning("resuming from the checkpoint before it: %s", path)
                    self._verified = path
                if components is not None:
                    self._read(path, components)
            except DamagedFileError as err:
                self._damaged[path] = err
                log.warning("checkpoint %s is damaged (%s); it is not used", path, err)
                continue
            return path
        if not candidates:
            return None
        err = self._damaged[candidates[0]]
        raise CheckpointDamagedError(
            f"{err.path} is damaged ({err.reason}), and no other checkpoint of "
            f"{self.directory} is whole. Fix: delete {self.directory} to restart this stage"
        )

    def load(self, path: Path, components: Mapping[str, Any]) -> Path:
        """Restores those of ``components`` that ``path`` holds, and the global generators."""
        try:
            self._read(path, components)
        except DamagedFileError as err:
            raise CheckpointDamagedError(
                f"{err.path} is damaged ({err.reason}). Fix: delete {path} to resume from the "
                f"checkpoint before it, or delete {self.directory} to restart this stage"
            ) from err
        return path

    def _read(self, path: Path, components: Mapping[str, Any]) -> None:
        """Loads ``path`` into ``components``; :class:`DamagedFileError` where it cannot."""
        if path != self._verified:
            verify_checkpoint(path)
            self._verified = path
        try:
            saved = Checkpoint.manifest(path)["components"]
            selected = {k: v for k, v in components.items() if k in saved}
            self._checkpoint(selected).load(path)
        except (CheckpointError, OSError, RuntimeError, ValueError, KeyError, TypeError) as err:
            if isinstance(err.__cause__, CheckpointFormatError):  # wrapped by torchrl
                raise CheckpointDamagedError(
                    f"{path} was written by an earlier version of torchrl-stages, whose loops "
                    f"kept another state ({err.__cause__}). Fix: delete {self.directory} to "
                    "restart this stage, or finish the run with the version that wrote it"
                ) from err
            why = f"it cannot be read back: {type(err).__name__}: {str(err)[:200]}"
            raise DamagedFileError(path, why) from err
        self._after(_frames(path))

    def clear(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)
        self._verified, self._damaged = None, {}


def _frames(path: Path) -> int:
    return int(path.name.removeprefix(f"{PREFIX}-"))
