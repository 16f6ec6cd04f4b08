"""The stacked policy: one policy per stage, each batch element routed by its stage tag."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from itertools import compress

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn


class StackedPolicy(TensorDictModuleBase):
    """Runs, for every batch element, the policy of its stage (its ``stage_key`` entry, else
    ``stage_fn(td)``); an output of other stages is zero there.

    Each stage's policy runs on the whole batch, but not a stage absent from it unless
    ``skip_absent=False`` (exploring policies then draw the same random numbers at every call).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> p0 = TensorDictModule(lambda o: o[..., :1] * 0, ["observation"], ["action"])
        >>> p1 = TensorDictModule(lambda o: o[..., :1] * 0 + 1, ["observation"], ["action"])
        >>> td = TensorDict(observation=torch.zeros(3, 2), stage=torch.tensor([[0], [1], [0]]),
        ...                 batch_size=[3])
        >>> StackedPolicy([p0, p1])(td)["action"].squeeze(-1)
        tensor([0., 1., 0.])
    """

    def __init__(
        self,
        policies: Sequence[TensorDictModuleBase],
        *,
        stage_fn: Callable[[TensorDictBase], torch.Tensor] | None = None,
        stage_key: NestedKey = "stage",
        skip_absent: bool = True,
    ) -> None:
        super().__init__()
        self.policies = nn.ModuleList(policies)
        self.stage_fn, self.stage_key, self.skip_absent = stage_fn, stage_key, skip_absent
        # each output's trailing shape and dtype, from the first call (every stage runs in it)
        self._outputs: dict[NestedKey, tuple[torch.Size, torch.dtype]] | None = None
        routing = [] if stage_fn is not None else [stage_key]
        self.in_keys = list(dict.fromkeys([*routing, *(k for p in policies for k in p.in_keys)]))
        self.out_keys = list(dict.fromkeys(k for p in policies for k in p.out_keys))

    def stage(self, tensordict: TensorDictBase) -> torch.Tensor:
        """int64 ``[*batch]``."""
        stage = tensordict.get(self.stage_key, None)
        if stage is not None:
            return stage.squeeze(-1)
        if self.stage_fn is None:
            raise KeyError(
                f"the input has no {self.stage_key!r} entry. Fix: tag the env with "
                "StageTransform(stage_fn, num_stages), or build the policy with "
                "StackedPolicy(policies, stage_fn=...) (load_policy does)"
            )
        return self.stage_fn(tensordict).to(torch.int64).reshape(tensordict.batch_size)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        stage = self.stage(tensordict)
        present = [True] * len(self.policies)
        if self.skip_absent and self._outputs is not None:
            present = torch.bincount(stage.reshape(-1), minlength=len(self.policies)).tolist()
        merged: dict[NestedKey, torch.Tensor] = {}
        for k, policy in compress(enumerate(self.policies), present):
            rows = stage == k
            out = policy(tensordict.select(*policy.in_keys).clone(False))
            for key in policy.out_keys:
                value = out.get(key)
                mask = rows.reshape(*rows.shape, *([1] * (value.ndim - rows.ndim)))
                merged[key] = torch.where(mask, value, merged.get(key, torch.zeros_like(value)))
        if self._outputs is None:
            self._outputs = {k: (v.shape[stage.ndim :], v.dtype) for k, v in merged.items()}
        device = next(iter(merged.values())).device if merged else stage.device
        for key, (shape, dtype) in self._outputs.items():
            if key not in merged:  # written only by stages absent from this batch
                merged[key] = torch.zeros(*stage.shape, *shape, dtype=dtype, device=device)
        return tensordict.update(merged)
