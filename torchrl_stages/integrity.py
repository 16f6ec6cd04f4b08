"""Atomic writes, and SHA-256 checksums of the files a run writes, verified before anything
is read back (a file may be truncated by a full disk, damaged by a copy, or crafted)."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path

CHECKSUMS = "sha256.json"


class DamagedFileError(RuntimeError):
    """A file (``path``) differs from what was recorded when it was written."""

    def __init__(self, path: str | Path, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = Path(path)
        self.reason = reason


def sha256_file(path: str | Path) -> str:
    with Path(path).open("rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def _files(directory: Path) -> set[str]:
    files = (p for p in directory.rglob("*") if p.is_file() or p.is_symlink())
    return {p.relative_to(directory).as_posix() for p in files} - {CHECKSUMS}


def write_checksums(directory: str | Path) -> None:
    """Records the SHA-256 of every file under ``directory`` in its ``sha256.json``."""
    directory = Path(directory)
    sums = {name: sha256_file(directory / name) for name in _files(directory)}
    (directory / CHECKSUMS).write_text(json.dumps(sums, indent=1, sort_keys=True))


def verify_checksums(directory: str | Path, suffixes: tuple[str, ...] = ()) -> None:
    """Checks ``directory`` holds exactly the files of its ``sha256.json`` (with ``suffixes``:
    only those endings), same bytes; :class:`DamagedFileError` names the first that differs."""
    directory = Path(directory)
    record = directory / CHECKSUMS
    try:
        sums = json.loads(record.read_text())
        if not isinstance(sums, dict) or not all(isinstance(v, str) for v in sums.values()):
            raise ValueError("not a mapping of file names to checksums")
    except FileNotFoundError:
        raise DamagedFileError(directory, f"no {CHECKSUMS} (not written by this version)") from None
    except (OSError, ValueError) as err:  # JSON and UTF-8 errors are ValueErrors
        raise DamagedFileError(record, f"unreadable ({type(err).__name__})") from err
    present = _files(directory)
    for name in sorted(present | sums.keys()):
        path = directory / name
        if name not in sums:
            raise DamagedFileError(path, "a file that was never written there")
        if name not in present:
            raise DamagedFileError(path, "missing")
        if path.is_symlink():
            raise DamagedFileError(path, "a link where a file was written")
        if suffixes and not name.endswith(suffixes):
            raise DamagedFileError(path, f"not a payload file ({', '.join(suffixes)})")
        if sha256_file(path) != sums[name]:
            raise DamagedFileError(path, "its bytes differ from those written")


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Writes ``path`` through a temporary file renamed into place: on error it is unchanged."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        write(tmp)
        _fsync(tmp)  # on disk before it replaces anything (a machine crash keeps one of the two)
        os.replace(tmp, path)
        _fsync(path.parent)
    except OSError as err:
        if err.filename is None:
            err.filename = str(path)
        raise
    finally:
        tmp.unlink(missing_ok=True)


def ensure_free_space(directory: Path, nbytes: int) -> None:
    """Raises ``OSError(ENOSPC)`` naming ``directory`` when its disk has less than ``nbytes``
    free: writing memory-mapped files there would end the process with SIGBUS instead."""
    existing = Path(directory)
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    free = shutil.disk_usage(existing).free
    if nbytes > free:
        raise OSError(
            errno.ENOSPC,
            f"{os.strerror(errno.ENOSPC)} ({nbytes / 2**20:.1f} MiB needed, "
            f"{free / 2**20:.1f} MiB free)",
            str(directory),
        )


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # a directory on a file system that cannot sync it
        if not path.is_dir():
            raise
    finally:
        os.close(fd)
