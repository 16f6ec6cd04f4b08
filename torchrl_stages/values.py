"""State-value adapters: how a trained stage hands V(s) to the stage before it.

Each adapter is a TensorDict module that reads the stage's observation keys and writes
``"state_value"`` (shape ``[*batch, 1]``). :class:`~torchrl_stages.transforms.StageTransform`
freezes the adapter it is given and runs it on the first state of the next stage.
"""

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
    """A deep copy of ``module`` holding ``params`` (e.g. a loss module's target parameters).

    With ``live`` the copy reads ``params`` themselves (no copy of their values, no gradients):
    it follows them as they are updated in place, e.g. by a target-network updater.
    """
    module = copy.deepcopy(module)
    if not live:
        TensorDict.from_module(module).data.update_(params.data)
        return module
    params.data.to_module(module)
    return module.requires_grad_(False).eval()


def _unique(keys: Sequence[NestedKey]) -> list[NestedKey]:
    out: list[NestedKey] = []
    for key in keys:
        if key not in out:
            out.append(key)
    return out


class QMaxValue(TensorDictModuleBase):
    """``V(s) = max_a Q(s, a)`` of a discrete Q-value network (DQN).

    On a ``QValueActor`` (what DQN learners build) it calls the actor's network on the input
    tensors directly, without the TensorDict modules around it: the same Q-values, bit for bit,
    for a fraction of the overhead (the value runs on every env step that leaves a stage).

    Args:
        qvalue_net: a module writing ``action_value_key`` (e.g. a ``QValueActor``).

    Keyword Args:
        action_value_key: where ``qvalue_net`` writes the Q-values of all actions.
        out_key: where the state value is written.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> q = TensorDictModule(lambda obs: obs * 2, ["observation"], ["action_value"])
        >>> v = QMaxValue(q)
        >>> v(TensorDict(observation=torch.tensor([[1.0, 3.0]]), batch_size=[1]))["state_value"]
        tensor([[6.]])
    """

    def __init__(
        self,
        qvalue_net: TensorDictModuleBase,
        *,
        action_value_key: NestedKey = "action_value",
        out_key: NestedKey = "state_value",
    ) -> None:
        super().__init__()
        self.qvalue_net = qvalue_net
        self.action_value_key = action_value_key
        self.in_keys = list(qvalue_net.in_keys)
        self.out_keys = [out_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        network = self._network()
        if network is not None:
            q = network.module(*(tensordict.get(key) for key in network.in_keys))
        else:
            td = self.qvalue_net(tensordict.select(*self.in_keys).clone(False))
            q = td.get(self.action_value_key)
        tensordict.set(self.out_keys[0], q.max(-1, keepdim=True).values)
        return tensordict

    def _network(self) -> TensorDictModule | None:
        """The plain ``TensorDictModule`` that writes a ``QValueActor``'s action values, when
        calling its ``module`` on the input tensors is all it does (``None``: run the whole
        ``qvalue_net``)."""
        net = self.qvalue_net
        if not isinstance(net, QValueActor):
            return None
        first = net.module[0]
        if (
            type(first) is not TensorDictModule
            or first.method is not None
            or first.method_kwargs
            or list(first.out_keys) != [self.action_value_key]
        ):
            return None
        return first


class ActorCriticValue(TensorDictModuleBase):
    """``V(s) = min_i Q_i(s, mu(s))`` over one critic (DDPG) or several (TD3's twin critics).

    Args:
        actor: deterministic actor writing the action its critics read (no exploration noise).
        critics: one or more modules reading the actor's output and writing ``value_key``.

    Keyword Args:
        value_key: the critics' output key.
        out_key: where the state value is written.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> actor = TensorDictModule(lambda o: -o, ["observation"], ["action"])
        >>> q1 = TensorDictModule(lambda o, a: (o - a).sum(-1, True), ["observation", "action"],
        ...                       ["state_action_value"])
        >>> q2 = TensorDictModule(lambda o, a: o.sum(-1, True), ["observation", "action"],
        ...                       ["state_action_value"])
        >>> v = ActorCriticValue(actor, [q1, q2])
        >>> v(TensorDict(observation=torch.tensor([[1.0]]), batch_size=[1]))["state_value"]
        tensor([[1.]])
    """

    def __init__(
        self,
        actor: TensorDictModuleBase,
        critics: Sequence[TensorDictModuleBase],
        *,
        value_key: NestedKey = "state_action_value",
        out_key: NestedKey = "state_value",
    ) -> None:
        super().__init__()
        if not critics:
            raise ValueError("ActorCriticValue needs at least one critic.")
        self.actor = actor
        self.critics = nn.ModuleList(critics)
        self.value_key = value_key
        produced = set(actor.out_keys)
        critic_keys = [k for c in critics for k in c.in_keys if k not in produced]
        self.in_keys = _unique([*actor.in_keys, *critic_keys])
        self.out_keys = [out_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        td = self.actor(tensordict.select(*self.in_keys).clone(False))
        values = [critic(td.clone(False)).get(self.value_key) for critic in self.critics]
        tensordict.set(self.out_keys[0], torch.stack(values).amin(0))
        return tensordict
