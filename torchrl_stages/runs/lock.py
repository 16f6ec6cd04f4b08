"""One writer per run directory: an exclusive OS lock held for the whole run.

Two ``stages-train`` processes started into the same ``hydra.run.dir`` would both find the
directory free and both train into it. :class:`RunLock` takes ``fcntl.flock`` on
``.stages/lock`` before the directory is checked and keeps it until the run ends; the kernel
releases it when the process dies (also on SIGKILL), so a killed run never leaves the
directory locked. The holder writes who it is (host, process id, start time, command) into
the lock file, which a refused process quotes.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no advisory locks, one writer is on you
    fcntl = None

LOCK_DIR = ".stages"
LOCK_FILE = "lock"


class RunLockedError(RuntimeError):
    """Another process holds the run directory (``holder``: who, in words)."""

    holder: str = "holder unknown"


class RunLock:
    """An exclusive lock on the run directory ``path`` (``path/.stages/lock``).

    Examples:
        >>> import tempfile
        >>> run = tempfile.mkdtemp()
        >>> first = RunLock(run).acquire()
        >>> try:
        ...     RunLock(run).acquire()
        ... except RunLockedError as err:
        ...     print("is in use by another process" in str(err))
        True
        >>> first.release()
        >>> RunLock(run).acquire().release()
    """

    def __init__(self, path: str | Path, file: str | Path | None = None) -> None:
        self.path = Path(path)
        # another lock file than the run directory's (the stage store's, one per stage)
        self.file = Path(file) if file is not None else self.path / LOCK_DIR / LOCK_FILE
        self._fd: int | None = None
        self.created_dir = False

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> RunLock:
        """Takes the lock without waiting; raises :class:`RunLockedError` naming the holder."""
        if self._fd is not None:
            return self
        return self._acquire()

    def wait(self, poll: float, waiting: Callable[[str], None]) -> RunLock:
        """Takes the lock, waiting for its holder: ``waiting(holder)`` runs before every
        ``poll`` seconds of sleep (it may raise to stop waiting, e.g. on a stop request)."""
        while True:
            try:
                return self.acquire()
            except RunLockedError as err:
                waiting(err.holder)
                time.sleep(poll)

    def _acquire(self) -> RunLock:
        directory = self.file.parent
        self.created_dir = not directory.exists()
        directory.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.file, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
            if fcntl is None:
                break
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode("utf-8", "replace").strip()
                os.close(fd)
                err = RunLockedError(
                    f"{self.path} is in use by another process ({_describe(holder)}): one "
                    "process at a time trains or evaluates a run directory. Fix: wait for it "
                    "to end (or stop it), or pick another hydra.run.dir"
                )
                err.holder = _describe(holder)
                raise err from None
            try:  # the file locked is still the lock file (a refused process may remove it)
                if os.stat(self.file).st_ino == os.fstat(fd).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        self._fd = fd
        return self

    def announce(self) -> None:
        """Writes who holds the lock into the lock file (once the run goes ahead)."""
        if self._fd is None:
            return
        holder = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "since": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join(sys.argv)[:500],
        }
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, json.dumps(holder).encode(), 0)

    def release(self, remove: bool = False) -> None:
        """Releases the lock (``remove``: also deletes the lock file and, if this lock created
        it and it is empty, ``.stages/``: a refused run leaves nothing behind)."""
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


def _describe(holder: str) -> str:
    try:
        info = json.loads(holder)
        return f"process {info['pid']} on {info['host']} since {info['since']}: {info['command']}"
    except (ValueError, KeyError, TypeError):
        return "holder unknown"
