"""Replay storage and buffers of the stage loops."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, is_tensor_collection
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer


class GatherStorage(LazyTensorStorage):
    """A :class:`~torchrl.data.LazyTensorStorage` whose reads of a 1-D index tensor gather each
    entry with ``index_select``.

    The same elements as the advanced indexing of its parent (``storage[index]``), which on
    image-shaped entries is several times slower: a 10 x 10 ``uint8`` window costs about 20 us
    per 256 indices that way against about 3 us. Other indices (ints, slices, masks) and
    non-TensorDict storages read as in the parent; checkpoints are the parent's.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import TensorDictReplayBuffer
        >>> rb = TensorDictReplayBuffer(storage=GatherStorage(100))
        >>> _ = rb.extend(TensorDict(window=torch.zeros(10, 1, 4, 4, dtype=torch.uint8),
        ...                          next=TensorDict(reward=torch.ones(10, 1), batch_size=[10]),
        ...                          batch_size=[10]))
        >>> sample = rb.sample(6)
        >>> sample["window"].shape, sample["next"].batch_size
        (torch.Size([6, 1, 4, 4]), torch.Size([6]))
    """

    def get(self, index: Any) -> Any:
        storage = self._storage
        if (
            isinstance(index, torch.Tensor)
            and index.ndim == 1
            and index.dtype != torch.bool
            and self.initialized
            and self.ndim == 1
            and is_tensor_collection(storage)
        ):
            # indices drawn from [0, len) (the sampler's): the unfilled tail is never read
            return storage.apply(lambda x: x.index_select(0, index), batch_size=index.shape)
        return super().get(index)


def stage_replay_buffer(
    size: int, device: torch.device | str, **kwargs: Any
) -> TensorDictReplayBuffer:
    """A stage loop's replay buffer: a :class:`GatherStorage` of ``size`` transitions on
    ``device`` (the learner's, where its batches are read); ``kwargs`` go to the buffer.

    Examples:
        >>> rb = stage_replay_buffer(100, "cpu", batch_size=4)
        >>> type(rb.storage).__name__, rb.storage.max_size
        ('GatherStorage', 100)
    """
    return TensorDictReplayBuffer(storage=GatherStorage(int(size), device=device), **kwargs)


class SeedReplayBuffer:
    """One uniform replay buffer per seed, in one storage ``[num_seeds, size]``.

    :meth:`extend` takes a seed-major batch (its first dimension grouped by seed, as a
    seed-stacked learner's envs collect it) and appends each seed's part to its own ring;
    :meth:`sample` returns ``[num_seeds, batch_size]`` transitions, each seed's drawn uniformly
    from its own part with its own indices, in one gather. (torchrl's buffers keep one ring and
    one sampler; N of them would cost N samples and a stack per update.)

    Examples:
        >>> from tensordict import TensorDict
        >>> rb = SeedReplayBuffer(4, num_seeds=2)
        >>> rb.extend(TensorDict(x=torch.tensor([0, 1, 10, 11]), batch_size=[4]))
        >>> len(rb), rb.sample(3)["x"].shape
        (2, torch.Size([2, 3]))
        >>> bool((rb.sample(5)["x"][1] >= 10).all())  # seed 1 only ever sees its own
        True
        >>> rb.sample(5, rows=torch.tensor([1]))["x"].shape  # seed 1's alone
        torch.Size([1, 5])
    """

    def __init__(self, size: int, *, num_seeds: int, device: torch.device | str = "cpu") -> None:
        self.size, self.num_seeds, self.device = int(size), int(num_seeds), torch.device(device)
        self.storage = None
        self.cursor = 0
        self.count = 0

    def __len__(self) -> int:
        """Transitions held per seed."""
        return self.count

    def extend(self, batch) -> None:
        n = self.num_seeds
        batch = batch.reshape(n, -1).to(self.device)
        m = batch.shape[1]
        if self.storage is None:
            self.storage = batch.apply(
                lambda x: torch.empty((n, self.size, *x.shape[2:]), dtype=x.dtype, device=x.device),
                batch_size=[n, self.size],
            )
        if m > self.size:  # only the newest fit
            batch, m = batch[:, m - self.size :], self.size
        index = (self.cursor + torch.arange(m, device=self.device)) % self.size
        for key, value in batch.items(True, True):
            self.storage.get(key)[:, index] = value
        self.cursor = (self.cursor + m) % self.size
        self.count = min(self.count + m, self.size)

    def state_dict(self) -> dict[str, Any]:
        """The transitions held (``[num_seeds, len(self)]``, nested dicts of tensors), the ring's
        cursor and its length: what :meth:`load_state_dict` restores."""
        held = None if self.storage is None else self.storage[:, : self.count].to_dict()
        return {"storage": held, "cursor": self.cursor, "count": self.count}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        count, cursor = int(state["count"]), int(state["cursor"])
        if not (0 <= count <= self.size and 0 <= cursor < max(self.size, 1)):
            raise ValueError(f"count {count} / cursor {cursor} outside a ring of {self.size}")
        self.storage, self.cursor, self.count = None, cursor, count
        if state["storage"] is None:
            return
        held = TensorDict(state["storage"], batch_size=[self.num_seeds, count], device=self.device)
        self.storage = held.apply(
            lambda x: torch.empty(
                (self.num_seeds, self.size, *x.shape[2:]), dtype=x.dtype, device=x.device
            ),
            batch_size=[self.num_seeds, self.size],
        )
        self.storage[:, :count] = held

    def sample(self, batch_size: int, rows: torch.Tensor | None = None):
        """``[num_seeds, batch_size]`` transitions; with ``rows`` (seed indices),
        ``[len(rows), batch_size]`` of those seeds only."""
        if rows is None:
            rows = torch.arange(self.num_seeds, device=self.device)
        n = rows.numel()
        index = torch.randint(self.count, (n, batch_size), device=self.device)
        rows = rows.to(self.device).unsqueeze(1)
        return self.storage.apply(lambda x: x[rows, index], batch_size=[n, batch_size])
