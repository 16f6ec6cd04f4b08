"""Network builders shared by the learners."""

from __future__ import annotations

import math

import torch
from torch import nn
from torchrl.modules import MLP
from torchrl.modules.models.models import DuelingMlpDQNet


class FourierFeatures(nn.Module):
    """``x -> [x, sin(2^k pi x), cos(2^k pi x)]`` for ``k < num_octaves`` (per input feature).

    Low-dimensional coordinate inputs (a grid cell, a joint angle) make plain MLPs smooth at the
    scale of one cell; the encoding lets a small network represent sharp changes, such as a
    move that is blocked at a wall but not one cell before it.

    Examples:
        >>> FourierFeatures(2)(torch.zeros(3, 2)).shape
        torch.Size([3, 10])
    """

    def __init__(self, num_octaves: int) -> None:
        super().__init__()
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(num_octaves), persistent=False)

    def out_features(self, in_features: int) -> int:
        return in_features * (1 + 2 * len(self.freqs))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = torch.cat(inputs, -1)
        angles = (x.unsqueeze(-1) * self.freqs).flatten(-2)
        return torch.cat([x, angles.sin(), angles.cos()], -1)


class _Encoded(nn.Module):
    def __init__(self, encoder: nn.Module, body: nn.Module) -> None:
        super().__init__()
        self.encoder, self.body = encoder, body

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.body(self.encoder(*inputs))


def mlp(in_features: int, out_features: int, num_cells: list[int], fourier: int = 0) -> nn.Module:
    """An MLP over the concatenated inputs, optionally after :class:`FourierFeatures`."""
    if fourier <= 0:
        return MLP(in_features=in_features, out_features=out_features, num_cells=num_cells)
    features = FourierFeatures(fourier)
    body = MLP(
        in_features=features.out_features(in_features),
        out_features=out_features,
        num_cells=num_cells,
    )
    return _Encoded(features, body)


def qvalue_net(
    in_features: int,
    num_actions: int,
    num_cells: list[int],
    *,
    dueling: bool = False,
    fourier: int = 0,
) -> nn.Module:
    """Q-values of every action: an MLP, or a dueling one (``Q = V + A - mean(A)``, the last
    hidden width feeding separate value and advantage heads)."""
    if not dueling:
        return mlp(in_features, num_actions, num_cells, fourier)
    encoder = FourierFeatures(fourier) if fourier > 0 else None
    width_in = encoder.out_features(in_features) if encoder is not None else in_features
    *trunk, width = num_cells
    net = DuelingMlpDQNet(
        num_actions,
        mlp_kwargs_feature={
            "in_features": width_in,
            "num_cells": trunk,
            "out_features": width,
            "activation_class": nn.ReLU,
        },
        mlp_kwargs_output={
            "in_features": width,
            "num_cells": width,
            "depth": 1,
            "activation_class": nn.ReLU,
        },
    )
    return net if encoder is None else _Encoded(encoder, net)
