"""Replay storage and buffers of the stage loops."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import is_tensor_collection
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
