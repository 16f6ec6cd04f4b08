"""SIGTERM, SIGINT and SIGUSR1 end a run cleanly: the loops write a checkpoint at the next safe
point and raise :class:`Interrupted`; ``resume=true`` continues bitwise."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGUSR1)

_requested: int | None = None


class Interrupted(Exception):  # noqa: N818 - an outcome, not an error
    """A run stopped on signal ``signum`` in ``where`` after saving what it needs to resume."""

    def __init__(self, signum: int, where: str) -> None:
        self.signum, self.where = int(signum), where
        self.signal_name = signal.Signals(self.signum).name
        self.exit_code = 128 + self.signum  # 143 for SIGTERM, 130 for SIGINT, 138 for SIGUSR1
        super().__init__(f"interrupted by {self.signal_name} in {where}")


def requested() -> int | None:
    """The signal that asked the run to stop, if any."""
    return _requested


def stop_if_asked(where: str) -> None:
    """Raises :class:`Interrupted` if a stop was requested (call it where the state is saved)."""
    if _requested is not None:
        raise Interrupted(_requested, where)


@contextmanager
def handle_signals() -> Iterator[None]:
    """Records :data:`SIGNALS` as stop requests in the block (main thread only). A second
    signal gets the previous handler; a launcher's handler runs once the state is saved.

    Examples:
        >>> import os, signal
        >>> with handle_signals():
        ...     os.kill(os.getpid(), signal.SIGUSR1)
        ...     signal.Signals(requested()).name
        'SIGUSR1'
        >>> requested() is None
        True
    """
    global _requested
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}

    def on_signal(signum: int, frame: object) -> None:
        global _requested
        _requested = signum
        for other, handler in previous.items():  # a second signal ends the process
            signal.signal(other, handler)

    _requested = None
    for signum in SIGNALS:
        signal.signal(signum, on_signal)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        received, _requested = _requested, None
        handler = previous.get(received)
        if callable(handler) and handler is not signal.default_int_handler:
            handler(received, None)  # the launcher's own reaction, now that state is saved
