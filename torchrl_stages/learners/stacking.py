"""Seed-stacked learners: N seeds' networks in one set of tensors (seed ``i``'s layer in row
``i``), their inputs laid out seed-major."""

from __future__ import annotations

import copy
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from contextvars import ContextVar

import torch
from torch import nn

_SEEDS: ContextVar[int | None] = ContextVar("torchrl_stages_seeds", default=None)
_ROWS: ContextVar[torch.Tensor | None] = ContextVar("torchrl_stages_seed_rows", default=None)
current_seeds = _SEEDS.get  # how many seeds the networks built now stack (:func:`stacked_networks`)
current_rows = _ROWS.get  # the seeds computed now (:func:`update_rows`)


class _StackedLayer(nn.Module):
    """``num_seeds`` freshly initialized twins of ``layer``, their ``weight`` and ``bias``
    stacked, read for the seeds computed now (:func:`update_rows`)."""

    def __init__(self, layer: nn.Module, num_seeds: int) -> None:
        super().__init__()
        twins = [copy.deepcopy(layer) for _ in range(num_seeds)]
        for twin in twins:
            twin.reset_parameters()  # the draws of building it anew
        self.weight = nn.Parameter(torch.stack([twin.weight.detach() for twin in twins]))
        self.bias = nn.Parameter(torch.stack([twin.bias.detach() for twin in twins]))

    def _rows(self) -> tuple[torch.Tensor, torch.Tensor]:
        rows = _ROWS.get()
        if rows is None:
            return self.weight, self.bias
        return self.weight[rows], self.bias[rows]


class StackedLinear(_StackedLayer):
    """``nn.Linear`` for ``num_seeds`` seeds in one ``baddbmm`` (inputs ``[num_seeds * M, in]``
    or ``[num_seeds, M, in]``).

    Examples:
        >>> layer = StackedLinear(nn.Linear(3, 2), num_seeds=4)
        >>> x = torch.randn(4, 5, 3)
        >>> torch.allclose(layer(x)[1], x[1] @ layer.weight[1].T + layer.bias[1], atol=1e-6)
        True
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight, bias = self._rows()
        seed_major = x.reshape(weight.shape[0], -1, x.shape[-1])
        out = torch.baddbmm(bias.unsqueeze(1), seed_major, weight.transpose(1, 2))
        return out.reshape(*x.shape[:-1], out.shape[-1])


class StackedConv2d(_StackedLayer):
    """``nn.Conv2d`` for ``num_seeds`` seeds as one grouped convolution (seed ``i``: group ``i``).

    Examples:
        >>> layer = StackedConv2d(nn.Conv2d(1, 4, 3, stride=2, padding=1), num_seeds=3)
        >>> x = torch.randn(3 * 5, 1, 6, 6)
        >>> one = torch.nn.functional.conv2d(x[5:10], layer.weight[1], layer.bias[1], 2, 1)
        >>> torch.allclose(layer(x)[5:10], one, atol=1e-6)
        True
    """

    def __init__(self, layer: nn.Conv2d, num_seeds: int) -> None:
        super().__init__(layer, num_seeds)
        self.stride, self.padding = layer.stride, layer.padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight, bias = self._rows()
        n, (c, h, w) = weight.shape[0], x.shape[-3:]
        # seed-major [n, M, C, H, W] -> [M, n * C, H, W]: seed i's channels are group i
        grouped = x.reshape(n, -1, c, h, w).transpose(0, 1).reshape(-1, n * c, h, w)
        kernels, biases = weight.flatten(0, 1), bias.flatten()  # seed i's: group i
        out = nn.functional.conv2d(grouped, kernels, biases, self.stride, self.padding, groups=n)
        out = out.reshape(out.shape[0], n, weight.shape[1], *out.shape[-2:]).transpose(0, 1)
        return out.reshape(*x.shape[:-3], *out.shape[-3:])


def _stacked(name: str, layer: nn.Module, n: int) -> nn.Module | None:
    """The stacked twin of ``layer`` for ``n`` seeds (``None``: not a layer that stacks)."""
    if type(layer) is nn.Linear:
        if layer.bias is None:
            raise TypeError(f"{name}: a Linear without bias cannot be stacked for seeds")
        return StackedLinear(layer, n)
    if type(layer) is nn.Conv2d:
        plain = (
            layer.bias is not None
            and layer.groups == 1
            and layer.dilation == (1, 1)
            and layer.padding_mode == "zeros"
            and not isinstance(layer.padding, str)
        )
        if not plain:
            raise TypeError(
                f"{name}: only a Conv2d with bias, one group, no dilation and numeric zero "
                "padding can be stacked for seeds"
            )
        return StackedConv2d(layer, n)
    return None


@contextmanager
def _setting(var: ContextVar, value) -> Iterator[None]:
    token = var.set(value)
    try:
        yield
    finally:
        var.reset(token)


def stacked_networks(num_seeds: int | None) -> AbstractContextManager[None]:
    """Networks built inside are stacked for ``num_seeds`` seeds (``None``: not stacked)."""
    return _setting(_SEEDS, num_seeds)


def update_rows(rows: torch.Tensor | None) -> AbstractContextManager[None]:
    """Inside, stacked layers compute only the seeds ``rows`` (``None``: all), the others'
    gradients zero (a stage updates only its seeds that have not stopped)."""
    return _setting(_ROWS, rows)


def seed_rows(values: torch.Tensor) -> torch.Tensor:
    """``values`` held one per seed (``[N, ...]``) for the seeds computed now; a scalar as is."""
    rows = _ROWS.get()
    return values if rows is None or values.ndim == 0 else values[rows]


def per_seed(values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``values`` (one per seed computed now) shaped to broadcast against the seed-major
    ``like`` (``[n, ...]`` or ``[n * M, ...]``); a scalar as it is.

    Examples:
        >>> alpha = torch.tensor([1.0, 10.0])
        >>> per_seed(alpha, torch.ones(2, 3)).shape, per_seed(alpha, torch.ones(6, 4))[:, 0]
        (torch.Size([2, 1]), tensor([ 1.,  1.,  1., 10., 10., 10.]))
    """
    if values.ndim == 0:
        return values
    n, lead = values.shape[0], like.shape[0]
    if lead != n:
        values = values.repeat_interleave(lead // n)
    return values.reshape(lead, *[1] * (like.ndim - 1))


def stack_for_seeds(module: nn.Module) -> nn.Module:
    """``module`` with its layers stacked for the seeds of :func:`stacked_networks`."""
    n = current_seeds()
    if n is None:
        return module
    for name, old in list(module.named_modules()):
        new = _stacked(name, old, n)
        if new is None:
            continue
        if name:
            module.set_submodule(name, new)
        else:  # the module is itself the layer
            module = new
    for name, m in module.named_modules():
        own = next(m.parameters(recurse=False), None)
        if own is not None and not isinstance(m, _StackedLayer):
            raise TypeError(
                f"{name or type(m).__name__} ({type(m).__name__}) holds parameters that cannot "
                "be stacked for seeds: only Linear and Conv2d layers can"
            )
    return module


def seed_axes(learner: nn.Module) -> dict[str, int | None]:
    """The seeds' axis of each ``state_dict`` entry of a seed-stacked ``learner`` (``None``:
    shared), read off twins built for 1 and 2 seeds."""
    if "_seed_axes" in learner.__dict__:
        return learner.__dict__["_seed_axes"]
    twins = []
    with torch.random.fork_rng(devices=[]):
        for n in (1, 2):
            with stacked_networks(n):
                twins.append(type(learner)(learner.cfg, learner.specs).state_dict())
    axes: dict[str, int | None] = {}
    for key, one in twins[0].items():
        pairs = zip(one.shape, twins[1][key].shape, strict=True)
        axes[key] = next((i for i, (a, b) in enumerate(pairs) if a != b), None)
    learner.__dict__["_seed_axes"] = axes
    return axes


def stack_learners(stacked: nn.Module, learners: Sequence[nn.Module]) -> nn.Module:
    """Loads ordinary ``learners`` into their seed-stacked twin, seed ``i`` into row ``i``
    (shared entries from the first); returns ``stacked``."""
    if len(learners) != stacked.seeds:
        raise ValueError(f"{len(learners)} learners for {stacked.seeds} seeds")
    states, axes = [learner.state_dict() for learner in learners], seed_axes(stacked)
    merged = {
        k: states[0][k] if axes[k] is None else torch.stack([s[k] for s in states], axes[k])
        for k in stacked.state_dict()
    }
    stacked.load_state_dict(merged)
    stacked.num_updates = max(learner.num_updates for learner in learners)
    return stacked


def unstack_learner(stacked: nn.Module, seed: int, learner: nn.Module) -> nn.Module:
    """Loads row ``seed`` of ``stacked`` into the ordinary ``learner``; returns ``learner``."""
    axes = seed_axes(stacked)
    row = {
        k: v.clone() if axes[k] is None else v.select(axes[k], seed).clone()
        for k, v in stacked.state_dict().items()
    }
    learner.load_state_dict(row)
    learner.num_updates = stacked.num_updates
    return learner
