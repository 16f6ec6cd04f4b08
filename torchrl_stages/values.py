"""TensorDict modules that write a trained stage's ``V(s)`` as ``"state_value"``
(``[*batch, 1]``) for the stage before it."""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import QValueActor


def with_params(module: nn.Module, params: TensorDictBase, *, live: bool = False) -> nn.Module:
    """A deep copy of ``module`` holding a copy of ``params``; with ``live`` it reads ``params``
    themselves (no gradients), following their in-place updates."""
    module = copy.deepcopy(module)
    if not live:
        TensorDict.from_module(module).data.update_(params.data)
        return module
    params.data.to_module(module)
    return module.requires_grad_(False).eval()


class QMaxValue(TensorDictModuleBase):
    """``V(s) = max_a Q(s, a)`` of a module writing ``action_value_key`` (DQN); a
    ``QValueActor``'s network is called on the tensors directly (the same values, faster).

    Examples:
        >>> q = TensorDictModule(lambda obs: obs * 2, ["observation"], ["action_value"])
        >>> v = QMaxValue(q)
        >>> v(TensorDict(observation=torch.tensor([[1.0, 3.0]]), batch_size=[1]))["state_value"]
        tensor([[6.]])
    """

    def __init__(
        self, qvalue_net: TensorDictModuleBase, *, action_value_key: NestedKey = "action_value"
    ) -> None:
        super().__init__()
        self.qvalue_net, self.action_value_key = qvalue_net, action_value_key
        self.in_keys, self.out_keys = list(qvalue_net.in_keys), ["state_value"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        network = self._network()
        if network is not None:
            q = network.module(*(tensordict.get(key) for key in network.in_keys))
        else:
            td = self.qvalue_net(tensordict.select(*self.in_keys).clone(False))
            q = td.get(self.action_value_key)
        return tensordict.set("state_value", q.max(-1, keepdim=True).values)

    def _network(self) -> TensorDictModule | None:
        """A ``QValueActor``'s network module, when calling it is all the actor does."""
        first = self.qvalue_net.module[0] if isinstance(self.qvalue_net, QValueActor) else None
        plain = type(first) is TensorDictModule and first.method is None and not first.method_kwargs
        return first if plain and list(first.out_keys) == [self.action_value_key] else None


class ActorCriticValue(TensorDictModuleBase):
    """``V(s) = min_i Q_i(s, mu(s))`` over one critic (DDPG) or several (TD3's twins); the
    ``critics`` read the action ``actor`` writes and write ``"state_action_value"``.

    Examples:
        >>> actor = TensorDictModule(lambda o: -o, ["observation"], ["action"])
        >>> q = TensorDictModule(lambda o, a: o - a, ["observation", "action"],
        ...                      ["state_action_value"])
        >>> v = ActorCriticValue(actor, [q, q])
        >>> v(TensorDict(observation=torch.ones(1, 1), batch_size=[1]))["state_value"]
        tensor([[2.]])
    """

    def __init__(
        self, actor: TensorDictModuleBase, critics: Sequence[TensorDictModuleBase]
    ) -> None:
        super().__init__()
        if not critics:
            raise ValueError("ActorCriticValue needs at least one critic.")
        self.actor, self.critics = actor, nn.ModuleList(critics)
        critic_keys = [k for c in critics for k in c.in_keys if k not in actor.out_keys]
        self.in_keys = list(dict.fromkeys([*actor.in_keys, *critic_keys]))
        self.out_keys = ["state_value"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        td = self.actor(tensordict.select(*self.in_keys).clone(False))
        values = [critic(td.clone(False)).get("state_action_value") for critic in self.critics]
        return tensordict.set("state_value", torch.stack(values).amin(0))
