"""Periodic checkpoints of the stage in progress, on ``torchrl.checkpoint``.

A checkpoint holds everything the stage loop needs to go on as if it had never stopped: the
learner (weights, target networks, optimizers, exploration state, update count), the replay
buffer (``dumps``/``loads``), the collector (frames, running episodes, the env's state and
generator), the evaluation env's generator, the early-stop and best-weights bookkeeping, the
loop's counters, every process-global generator (``GlobalRNGState``: torch, numpy, Python) and
the length of every log file. ``torchrl.checkpoint.Checkpoint`` writes each one into a staging
directory and renames it into place, so a checkpoint on disk is always whole;
``CheckpointRotation`` keeps the last few.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from torchrl.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointRotation,
    GlobalRNGState,
    StateDictCheckpointAdapter,
)

PREFIX = "frames"


class StateOf:
    """Adapts a pair of functions to the ``state_dict`` / ``load_state_dict`` protocol.

    Examples:
        >>> box = {"n": 1}
        >>> state = StateOf(lambda: dict(box), box.update)
        >>> state.load_state_dict({"n": 2}); box["n"]
        2
    """

    def __init__(self, get: Callable[[], Any], set: Callable[[Any], None]) -> None:
        self._get, self._set = get, set

    def state_dict(self) -> Any:
        return self._get()

    def load_state_dict(self, state: Any) -> None:
        self._set(state)


class CheckpointDamagedError(RuntimeError):
    """A checkpoint on disk cannot be read back."""


class StageCheckpoints:
    """The rotated checkpoints of one stage in ``directory`` (``frames-<frames>`` entries).

    Args:
        directory: where this stage's checkpoints live (e.g. ``RUN/checkpoints/stage_3``).
        every: frames between two checkpoints (``0``: never).
        keep: how many of the newest checkpoints to keep.

    Examples:
        >>> import tempfile, torch
        >>> ckpts = StageCheckpoints(tempfile.mkdtemp(), every=100)
        >>> net = torch.nn.Linear(2, 1)
        >>> components = {"net": net, "counters": {"frames": 100}}
        >>> ckpts.due(99), ckpts.due(100)
        (False, True)
        >>> path = ckpts.save(100, components)
        >>> ckpts.load(ckpts.latest(), components) == path
        True
    """

    def __init__(self, directory: str | Path, every: int, keep: int = 2) -> None:
        self.directory = Path(directory)
        self.every, self.keep = int(every), int(keep)
        self._next = self.every

    def due(self, frames: int) -> bool:
        """Whether a checkpoint is due after ``frames`` frames (one per ``every`` frames)."""
        return self.every > 0 and frames >= self._next

    def _checkpoint(self, components: dict[str, Any]) -> Checkpoint:
        ckpt = Checkpoint(format="directory", rng=GlobalRNGState())
        torch_payload = StateDictCheckpointAdapter(payload_format="torch")
        for name, component in components.items():
            stateful = hasattr(component, "state_dict") and not hasattr(component, "dump")
            ckpt.register(name, component, adapter=torch_payload if stateful else None)
        return ckpt

    def save(self, frames: int, components: dict[str, Any]) -> Path:
        """Writes a checkpoint at ``frames`` (atomically) and prunes the old ones. Empty replay
        buffers are left out (an empty storage cannot be dumped; loading leaves it empty)."""
        components = {
            k: v for k, v in components.items() if not (hasattr(v, "dump") and len(v) == 0)
        }
        rotation = CheckpointRotation(self.directory, keep_last=self.keep, prefix=PREFIX)
        path = rotation.save(self._checkpoint(components), step=int(frames))
        self._next = (frames // self.every + 1) * self.every if self.every > 0 else 0
        return path

    def latest(self) -> Path | None:
        """The newest checkpoint of this stage, if any."""
        if not self.directory.is_dir():
            return None
        return CheckpointRotation(self.directory, keep_last=self.keep, prefix=PREFIX).latest()

    def load(self, path: Path, components: dict[str, Any]) -> Path:
        """Restores those of ``components`` that the checkpoint ``path`` holds (and the global
        generators)."""
        try:
            saved = Checkpoint.manifest(path)["components"]
            self._checkpoint({k: v for k, v in components.items() if k in saved}).load(path)
        except (CheckpointError, OSError, RuntimeError, ValueError, KeyError) as err:
            raise CheckpointDamagedError(
                f"{path} cannot be read back ({type(err).__name__}: {str(err)[:200]}). Fix: "
                f"delete it to resume from the checkpoint before it, or delete {self.directory} "
                "to restart this stage"
            ) from err
        frames = int(path.name.removeprefix(f"{PREFIX}-").removesuffix(".torchrl"))
        self._next = (frames // self.every + 1) * self.every if self.every > 0 else 0
        return path

    def clear(self) -> None:
        """Removes this stage's checkpoints (once the stage's final file is written)."""
        shutil.rmtree(self.directory, ignore_errors=True)
