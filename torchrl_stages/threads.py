"""The run's torch thread count, held against torchrl's batched envs, which reset it when they
close (more threads than asked train 10-40 times slower on a busy machine)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

_held: int | None = None


def keep_threads() -> None:
    """Puts the held thread count back if something changed it."""
    if _held is not None and torch.get_num_threads() != _held:
        torch.set_num_threads(_held)


@contextmanager
def hold_threads(threads: int) -> Iterator[None]:
    """Sets torch's intra-op threads and holds them there (:func:`keep_threads`) in the block.

    Examples:
        >>> with hold_threads(1):
        ...     torch.set_num_threads(2)  # e.g. a batched env closing
        ...     keep_threads()
        ...     torch.get_num_threads()
        1
    """
    global _held
    previous, _held = _held, int(threads)
    torch.set_num_threads(_held)
    try:
        yield
    finally:
        _held = previous
