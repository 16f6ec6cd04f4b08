"""The run's torch thread count, held against anything that changes it.

torchrl's batched envs call ``torch.set_num_threads`` when they close (also when one is
garbage-collected in the middle of a stage), so a run asked for one thread could train with
two. On a machine whose other cores are busy, a two-thread update then waits for a core at every
operation: 10-40 times slower. Inside :func:`hold_threads` the training loops call
:func:`keep_threads` at every batch and evaluation, which puts the count back.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

_held: int | None = None


def keep_threads() -> None:
    """Puts the held thread count back if something changed it (nothing held: no-op)."""
    if _held is not None and torch.get_num_threads() != _held:
        torch.set_num_threads(_held)


@contextmanager
def hold_threads(threads: int) -> Iterator[None]:
    """Sets torch's intra-op threads to ``threads`` and holds them there while the block runs.

    Examples:
        >>> with hold_threads(1):
        ...     torch.set_num_threads(2)  # e.g. a batched env closing
        ...     keep_threads()
        ...     torch.get_num_threads()
        1
    """
    global _held
    previous = _held
    _held = int(threads)
    torch.set_num_threads(_held)
    try:
        yield
    finally:
        _held = previous
