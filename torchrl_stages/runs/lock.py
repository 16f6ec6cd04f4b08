"""One writer per run directory: ``fcntl.flock`` on ``.stages/lock``, which the kernel releases
when the process dies (SIGKILL too)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import sys
import time
from pathlib import Path

from torchrl_stages.runs.layout import RunDirError

LOCK_DIR = ".stages"


class RunLockedError(RunDirError):
    """Another process (``holder``: who, in words) holds the lock of run directory ``path``."""

    def __init__(self, path: Path, holder: str) -> None:
        super().__init__(
            f"{path} is in use by another process ({holder}): one process at a time trains or "
            "evaluates a run directory. Fix: wait for it to end (or stop it), or pick another "
            "hydra.run.dir"
        )
        self.holder = holder


class RunLock:
    """An exclusive lock on the run directory ``path``, or on ``file``.

    Examples:
        >>> import tempfile
        >>> run = tempfile.mkdtemp()
        >>> with RunLock(run):  # doctest: +ELLIPSIS
        ...     RunLock(run).acquire()
        Traceback (most recent call last):
        torchrl_stages.runs.lock.RunLockedError: ... is in use by another process ...
        >>> RunLock(run).acquire().release()
    """

    def __init__(self, path: str | Path, file: str | Path | None = None) -> None:
        self.path = Path(path)
        self.file = Path(file) if file is not None else self.path / LOCK_DIR / "lock"
        self._fd: int | None = None
        self.created_dir = False

    def acquire(self) -> RunLock:
        if self._fd is not None:
            return self
        directory = self.file.parent
        self.created_dir = not directory.exists()
        directory.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.file, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode("utf-8", "replace").strip() or "holder unknown"
                os.close(fd)
                raise RunLockedError(self.path, holder) from None
            # the file locked is still the lock file (a refused process may remove it)
            with contextlib.suppress(FileNotFoundError):
                if os.stat(self.file).st_ino == os.fstat(fd).st_ino:
                    break
            os.close(fd)
        self._fd = fd
        return self

    def announce(self) -> None:
        since, command = time.strftime("%Y-%m-%dT%H:%M:%S%z"), " ".join(sys.argv)[:500]
        holder = f"process {os.getpid()} on {socket.gethostname()} since {since}: {command}"
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, holder.encode(), 0)

    def release(self, remove: bool = False) -> None:
        """Releases the lock; ``remove`` also deletes the lock file (and the directory it made)."""
        if self._fd is None:
            return
        if remove:
            self.file.unlink(missing_ok=True)
            if self.created_dir and not any(self.file.parent.iterdir()):
                self.file.parent.rmdir()
        os.close(self._fd)  # closing the descriptor releases the flock
        self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
