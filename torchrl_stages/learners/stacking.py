"""Seed-stacked learners: the networks of N seeds' learners in one set of tensors.

A learner built inside :func:`stacked_networks` (``make_learner(..., seeds=N)``) has every
``nn.Linear`` of the networks :mod:`~torchrl_stages.learners.networks` builds replaced by a
:class:`StackedLinear`: one weight ``[N, out, in]``, seed ``i``'s layer in row ``i``. Its inputs
are laid out seed-major (``[N * M, ...]`` or ``[N, M, ...]``: seed ``i``'s elements first come
seed ``i - 1``'s), so everything between two layers (activations, the dueling head's mean, the
Fourier features) runs on all seeds unchanged, and one ``baddbmm`` per layer replaces N
matrix products. Adam, the soft target update and every elementwise step then act on each seed
alone; the learners reduce their losses with :meth:`~torchrl_stages.learners.Learner.batch_mean`
(one loss per seed), and :meth:`~torchrl_stages.learners.Learner._step` clips each seed's
gradient by its own norm. :func:`stack_learners` loads N ordinary learners into a stacked one,
:func:`unstack_learner` takes seed ``i`` back out.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TYPE_CHECKING

import torch
from torch import nn

if TYPE_CHECKING:
    from torchrl_stages.learners.base import Learner

_SEEDS: ContextVar[int | None] = ContextVar("torchrl_stages_seeds", default=None)
_ROWS: ContextVar[torch.Tensor | None] = ContextVar("torchrl_stages_seed_rows", default=None)


class StackedLinear(nn.Module):
    """``num_seeds`` independent ``nn.Linear(in_features, out_features)`` layers in one module.

    ``weight`` is ``[num_seeds, out, in]`` and ``bias`` ``[num_seeds, out]`` (row ``i``: seed
    ``i``'s layer, initialized as ``nn.Linear`` initializes). The input's leading dimensions are
    seed-major: ``[num_seeds * M, in]``, ``[num_seeds, M, in]`` or any shape whose elements are
    grouped by seed in that order; the output has the input's leading dimensions.

    Examples:
        >>> layer = StackedLinear(3, 2, num_seeds=4)
        >>> layer(torch.zeros(4 * 5, 3)).shape, layer(torch.zeros(4, 5, 3)).shape
        (torch.Size([20, 2]), torch.Size([4, 5, 2]))
        >>> x = torch.randn(4, 5, 3)
        >>> torch.allclose(layer(x)[1], x[1] @ layer.weight[1].T + layer.bias[1], atol=1e-6)
        True
    """

    def __init__(self, in_features: int, out_features: int, *, num_seeds: int) -> None:
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        layers = [nn.Linear(in_features, out_features) for _ in range(num_seeds)]
        self.weight = nn.Parameter(torch.stack([layer.weight.detach() for layer in layers]))
        self.bias = nn.Parameter(torch.stack([layer.bias.detach() for layer in layers]))

    @property
    def num_seeds(self) -> int:
        return self.weight.shape[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight, bias, rows = self.weight, self.bias, _ROWS.get()
        if rows is not None:  # only these seeds' layers (update_rows)
            weight, bias = weight[rows], bias[rows]
        n = weight.shape[0]
        out = torch.baddbmm(
            bias.unsqueeze(1), x.reshape(n, -1, x.shape[-1]), weight.transpose(1, 2)
        )
        return out.reshape(*x.shape[:-1], out.shape[-1])

    def extra_repr(self) -> str:
        return f"in={self.in_features}, out={self.out_features}, num_seeds={self.num_seeds}"


def current_seeds() -> int | None:
    """The number of seeds networks are stacked for now (``None``: not stacked)."""
    return _SEEDS.get()


@contextmanager
def stacked_networks(num_seeds: int | None) -> Iterator[None]:
    """Networks built inside (by :mod:`~torchrl_stages.learners.networks`) are stacked for
    ``num_seeds`` seeds (:func:`stack_for_seeds`); ``None``: as usual.

    Examples:
        >>> from torchrl_stages.learners.networks import mlp
        >>> with stacked_networks(3):
        ...     net = mlp(4, 2, [8])
        >>> net(torch.zeros(3 * 7, 4)).shape, type(net[0]).__name__
        (torch.Size([21, 2]), 'StackedLinear')
    """
    token = _SEEDS.set(num_seeds)
    try:
        yield
    finally:
        _SEEDS.reset(token)


def current_rows() -> torch.Tensor | None:
    """The seeds (row indices) stacked layers compute now (:func:`update_rows`); ``None``: all."""
    return _ROWS.get()


@contextmanager
def update_rows(rows: torch.Tensor | None) -> Iterator[None]:
    """Inside, every :class:`StackedLinear` computes only the seeds ``rows`` (a 1-D index
    tensor; ``None``: all of them): inputs hold ``len(rows)`` seeds' elements, and the
    gradients of the other seeds' rows are zero. A stage of many seeds updates only the seeds
    that have not stopped this way, at the cost of those alone.

    Examples:
        >>> layer = StackedLinear(3, 2, num_seeds=4)
        >>> x = torch.randn(2, 5, 3)
        >>> with update_rows(torch.tensor([1, 3])):
        ...     y = layer(x)
        >>> torch.allclose(y[1], x[1] @ layer.weight[3].T + layer.bias[3], atol=1e-6)
        True
        >>> y.sum().backward()
        >>> layer.weight.grad[[0, 2]].abs().sum().item()
        0.0
    """
    token = _ROWS.set(rows)
    try:
        yield
    finally:
        _ROWS.reset(token)


def stack_for_seeds(module: nn.Module) -> nn.Module:
    """``module`` with each ``nn.Linear`` replaced by a :class:`StackedLinear` for the seeds of
    :func:`stacked_networks` (unchanged outside it). Raises ``TypeError`` for a module that
    holds parameters of another kind (e.g. a CNN's ``Conv2d``), which cannot be stacked."""
    n = current_seeds()
    if n is None:
        return module
    targets = [name for name, m in module.named_modules() if type(m) is nn.Linear]
    for name in targets:
        parent, _, attr = name.rpartition(".")
        old = module.get_submodule(name)
        if old.bias is None:
            raise TypeError(f"{name}: a Linear without bias cannot be stacked for seeds")
        new = StackedLinear(old.in_features, old.out_features, num_seeds=n)
        if parent or attr:
            setattr(module.get_submodule(parent), attr, new)
        else:
            module = new
    for name, m in module.named_modules():
        if not isinstance(m, StackedLinear) and any(True for _ in m.parameters(recurse=False)):
            raise TypeError(
                f"{name or type(m).__name__} ({type(m).__name__}) holds parameters that cannot "
                "be stacked for seeds: only Linear layers can (no image inputs)"
            )
    return module


def _seed_rows(
    stacked: dict[str, torch.Tensor], plain: dict[str, torch.Tensor], num_seeds: int
) -> dict[str, bool]:
    """Which entries of a stacked learner's ``state_dict`` hold one row per seed (the others are
    shared, e.g. an exploration schedule), checked against an ordinary learner's."""
    if stacked.keys() != plain.keys():
        raise ValueError("the stacked and the ordinary learner have different entries")
    rows = {}
    for key, value in stacked.items():
        other = plain[key]
        if value.ndim == other.ndim + 1 and value.shape == (num_seeds, *other.shape):
            rows[key] = True
        elif value.shape == other.shape:
            rows[key] = False
        else:
            raise ValueError(
                f"{key}: shape {tuple(value.shape)} is neither {tuple(other.shape)} nor "
                f"({num_seeds}, ...) of it"
            )
    return rows


def stack_learners(stacked: Learner, learners: Sequence[Learner]) -> Learner:
    """Loads ``learners`` (one per seed, ordinary) into ``stacked`` (their seed-stacked twin),
    seed ``i`` into row ``i``; returns ``stacked``. Entries shared by all seeds are taken from
    the first learner."""
    states = [learner.state_dict() for learner in learners]
    own = stacked.state_dict()
    rows = _seed_rows(own, states[0], len(learners))
    stacked.load_state_dict(
        {k: torch.stack([s[k] for s in states]) if rows[k] else states[0][k] for k in own}
    )
    stacked.num_updates = max(learner.num_updates for learner in learners)
    return stacked


def unstack_learner(stacked: Learner, seed: int, learner: Learner) -> Learner:
    """Loads row ``seed`` of the seed-stacked ``stacked`` into the ordinary ``learner`` (built
    with the same config and specs); returns ``learner``."""
    state, own = stacked.state_dict(), learner.state_dict()
    rows = _seed_rows(state, own, int(stacked.seeds or 0))
    learner.load_state_dict(
        {k: v[seed].clone() if rows[k] else v.clone() for k, v in state.items()}
    )
    learner.num_updates = stacked.num_updates
    return learner
