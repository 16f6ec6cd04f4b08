"""The optimizer and loss operations the algorithms share."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.func import functional_call
from torch.optim.optimizer import ParamsT, _global_optimizer_post_hooks, _global_optimizer_pre_hooks
from torchrl.objectives import SoftUpdate


class FusedSoftUpdate(SoftUpdate):
    """torchrl's ``SoftUpdate`` as one ``torch._foreach_lerp_`` over all parameter pairs.

    Examples:
        >>> from torchrl.modules import QValueActor
        >>> from torchrl.objectives import DQNLoss
        >>> net = QValueActor(nn.Linear(3, 2), action_space="categorical")
        >>> loss = DQNLoss(net, delay_value=True, action_space="categorical")
        >>> FusedSoftUpdate(loss, tau=0.5).step()
    """

    _pairs: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None

    def step(self) -> None:
        if self._pairs is None:  # torchrl's init_ has kept the distinct pairs
            sources = [p.data for p in self._sources.values(True, True)]
            self._pairs = (sources, [p.data for p in self._targets.values(True, True)])
        sources, targets = self._pairs
        torch._foreach_lerp_(targets, sources, 1.0 - float(self.eps))


class FusedAdam(torch.optim.Adam):
    """``Adam(fused=True)`` with :meth:`direct_step`: ``step``'s ``torch._fused_adam_`` call,
    bit for bit, without the Python around it (which costs more than the kernel on small nets).

    Examples:
        >>> net = nn.Linear(3, 1)
        >>> optimizer = FusedAdam(net.parameters(), lr=1e-2)
        >>> net(torch.ones(4, 3)).sum().backward()
        >>> optimizer.direct_step()
    """

    def __init__(self, params: ParamsT, lr: float = 1e-3, **kwargs: Any) -> None:
        super().__init__(params, lr=lr, fused=True, **kwargs)

    def _direct(self) -> bool:
        """Whether ``step`` is one kernel call: no hooks, plain fused Adam, float lr, every
        parameter with a gradient and state, one device and dtype."""
        hooks = self._optimizer_step_pre_hooks or self._optimizer_step_post_hooks
        if hooks or _global_optimizer_pre_hooks or _global_optimizer_post_hooks:
            return False
        kinds = set()
        for group in self.param_groups:
            if not group["fused"]:  # e.g. the state of a non-fused Adam was loaded
                return False
            if isinstance(group["lr"], torch.Tensor) or group["amsgrad"] or group["maximize"]:
                return False
            if group["differentiable"] or group.get("decoupled_weight_decay", False):
                return False
            for p in group["params"]:
                if p.grad is None or p not in self.state or p.grad.is_sparse:
                    return False
                kinds.add((p.device, p.dtype))
        return len(kinds) == 1

    @torch.no_grad()
    def direct_step(self) -> None:
        if not self._direct():
            self.step()
            return
        for group in self.param_groups:
            params = group["params"]
            if not params:
                continue
            states = [self.state[p] for p in params]
            steps = [state["step"] for state in states]
            beta1, beta2 = group["betas"]
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(
                params,
                [p.grad for p in params],
                [state["exp_avg"] for state in states],
                [state["exp_avg_sq"] for state in states],
                [],
                steps,
                amsgrad=False,
                lr=group["lr"],
                beta1=beta1,
                beta2=beta2,
                weight_decay=group["weight_decay"],
                eps=group["eps"],
                maximize=False,
            )


def total_grad_norm(grads: list[torch.Tensor]) -> torch.Tensor:
    """``torch.nn.utils.get_total_norm(grads)``, without its grouping for plain tensors."""
    kinds = {(g.device, g.dtype) for g in grads}
    plain = all(type(g) is torch.Tensor and g.device.type in ("cpu", "cuda") for g in grads)
    if len(kinds) != 1 or not plain:
        return torch.nn.utils.get_total_norm(grads)
    return torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)


def clip_seed_grads(
    grads: list[torch.Tensor], num_seeds: int, axes: Sequence[int], max_norm: float | None
) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_`` for each seed's gradients (seeds on axis ``axes[i]``):
    their 2-norms (``[num_seeds]``), each seed's clipped to ``max_norm`` (``None``: not clipped)."""
    pairs = list(zip(grads, axes, strict=True))
    per_tensor = [g.movedim(a, 0).reshape(num_seeds, -1).norm(dim=1) for g, a in pairs]
    norms = torch.linalg.vector_norm(torch.stack(per_tensor), 2.0, dim=0)
    if max_norm is None:
        return norms
    coef = (float(max_norm) / (norms + 1e-6)).clamp(max=1.0)
    for g, a in pairs:
        shape = [1] * g.ndim
        shape[a] = -1
        g.mul_(coef.view(shape))
    return norms


def td0_target(batch: TensorDictBase, next_value: torch.Tensor, gamma: float) -> torch.Tensor:
    """``r + gamma^steps (1 - terminated) V(s')``, torchrl's TD(0) estimate (``[B, 1]``)."""
    next_td, steps = batch.get("next"), batch.get("steps_to_next_obs", None)
    reward = next_td.get("reward")
    gamma = float(gamma)
    discount = gamma if steps is None else gamma ** steps.view_as(reward)
    alive = (~next_td.get("terminated")).to(reward.dtype)
    return reward + discount * alive * next_value


def stacked_calls(
    module: nn.Module,
    params: TensorDictBase,
    *inputs: torch.Tensor,
    detach: bool = False,
    count: int | None = None,
) -> list:
    """``module(*inputs)`` with each parameter set of the stacked ``params`` (twin critics; the
    first ``count``), or the one set of unstacked ``params``; ``detach``: no gradient to them."""
    flat = dict(params.flatten_keys(".").items())
    if detach:  # tensor by tensor: detaching the TensorDict costs more than the call itself
        flat = {n: p.detach() for n, p in flat.items()}
    if not params.batch_dims:
        return [functional_call(module, flat, inputs)]
    sets = params.batch_size[0] if count is None else count
    return [
        functional_call(module, {n: p[i] for n, p in flat.items()}, inputs) for i in range(sets)
    ]


def taken(values: torch.Tensor, action: torch.Tensor, one_hot: bool, lead: int = 0):
    """The values (``[..., num_actions]``) of the actions taken, ``[..., 1]``; ``lead``: leading
    dimensions of ``values`` that ``action`` lacks (twin critics)."""
    if one_hot:
        return (values * action.to(values.dtype)).sum(-1, keepdim=True)
    index = action.reshape(*values.shape[lead:-1], 1).expand(*values.shape[:-1], 1)
    return values.gather(-1, index)


def linear_schedule(start: float, end: float, frames: int, horizon: int) -> float:
    """Linear annealing from ``start`` to ``end`` over ``horizon`` frames, then constant."""
    if horizon <= 0:
        return end
    return end + (start - end) * max(0.0, 1.0 - frames / horizon)
