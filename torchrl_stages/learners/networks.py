"""Network builders shared by the learners (stacked for seeds inside
:func:`~torchrl_stages.learners.stacking.stacked_networks`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torchrl.modules import MLP
from torchrl.modules.models.models import DuelingMlpDQNet

from torchrl_stages.learners.stacking import stack_for_seeds


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


Shape = tuple[int, ...]


@dataclass(frozen=True)
class ConvSpec:
    """Layers of the CNN applied to image inputs ``(C, H, W)``: one entry per conv layer.

    Each layer is ``Conv2d(kernel, stride, padding=kernel // 2)`` + ReLU; the output is flattened.
    """

    channels: tuple[int, ...] = (16, 32)
    kernels: tuple[int, ...] = (3, 3)
    strides: tuple[int, ...] = (1, 2)


class ConvEncoder(nn.Module):
    """A small CNN over ``[*batch, C, H, W]`` images (any dtype, e.g. uint8 occupancy windows),
    flattened to ``[*batch, out_features]``.

    Examples:
        >>> ConvEncoder((1, 10, 10), ConvSpec())(torch.zeros(4, 7, 1, 10, 10)).shape
        torch.Size([4, 7, 800])
    """

    def __init__(self, shape: Shape, spec: ConvSpec) -> None:
        super().__init__()
        if not len(spec.channels) == len(spec.kernels) == len(spec.strides):
            raise ValueError(f"ConvSpec fields must have equal lengths, got {spec}.")
        self.shape = tuple(shape)
        layers: list[nn.Module] = []
        in_channels = self.shape[0]
        for channels, kernel, stride in zip(spec.channels, spec.kernels, spec.strides, strict=True):
            layers += [nn.Conv2d(in_channels, channels, kernel, stride, kernel // 2), nn.ReLU()]
            in_channels = channels
        self.net = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            self.out_features = int(self.net(torch.zeros(1, *self.shape)).shape[-1])

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        lead = image.shape[: image.ndim - 3]
        out = self.net(image.reshape(-1, *self.shape).to(torch.get_default_dtype()))
        return out.reshape(*lead, self.out_features)


class InputEncoder(nn.Module):
    """Features of a network's inputs: CNN features of each image input, concatenated with the
    vector inputs (after :class:`FourierFeatures` when ``fourier > 0``).

    Args:
        inputs: unbatched shape of each input, in call order: ``(C, H, W)`` images, ``(d,)``
            vectors.

    Examples:
        >>> enc = InputEncoder([(1, 10, 10), (2,)], cnn=ConvSpec(channels=(4,), kernels=(3,),
        ...                    strides=(2,)))
        >>> enc.out_features, enc(torch.zeros(5, 1, 10, 10), torch.zeros(5, 2)).shape
        (102, torch.Size([5, 102]))
    """

    def __init__(
        self, inputs: Sequence[Shape], *, fourier: int = 0, cnn: ConvSpec | None = None
    ) -> None:
        super().__init__()
        self.is_image = [len(shape) == 3 for shape in inputs]
        if any(len(shape) not in (1, 3) for shape in inputs):
            raise ValueError(f"inputs must be vectors (d,) or images (C, H, W), got {inputs}.")
        cnn = cnn or ConvSpec()
        self.convs = nn.ModuleList(ConvEncoder(s, cnn) for s in inputs if len(s) == 3)
        vector_dim = sum(s[0] for s in inputs if len(s) == 1)
        self.fourier = FourierFeatures(fourier) if fourier > 0 and vector_dim else None
        self.out_features = sum(conv.out_features for conv in self.convs) + (
            self.fourier.out_features(vector_dim) if self.fourier is not None else vector_dim
        )

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        images = iter(self.convs)
        features = [next(images)(x) for x, img in zip(inputs, self.is_image, strict=True) if img]
        vectors = [x for x, img in zip(inputs, self.is_image, strict=True) if not img]
        if vectors:
            features.append(self.fourier(*vectors) if self.fourier else torch.cat(vectors, -1))
        return torch.cat(features, -1)


class Chain(nn.Sequential):
    """``nn.Sequential`` whose first module takes several inputs (e.g. an image and a vector).

    Examples:
        >>> from tensordict.nn import NormalParamExtractor
        >>> loc, scale = Chain(InputEncoder([(2,), (2,)]), NormalParamExtractor())(
        ...     torch.zeros(3, 2), torch.ones(3, 2))
        >>> loc.shape, scale.shape
        (torch.Size([3, 2]), torch.Size([3, 2]))
    """

    def forward(self, *inputs: torch.Tensor):
        first, *rest = self
        out = first(*inputs)
        for module in rest:
            out = module(out)
        return out


class _Encoded(nn.Module):
    def __init__(self, encoder: nn.Module, body: nn.Module) -> None:
        super().__init__()
        self.encoder, self.body = encoder, body

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.body(self.encoder(*inputs))


class SharedEncoderCritic(nn.Module):
    """``Q(s, a) = body([encoder(s), a])``, over an input encoder shared with the actor.

    The encoder (e.g. the CNN of an image observation) is the actor's own module: features are
    laid out as in a critic with its own :class:`InputEncoder` (encoder features, then the
    action), only the encoder is not duplicated.

    Examples:
        >>> enc = InputEncoder([(1, 10, 10), (2,)], cnn=ConvSpec(channels=(4,), kernels=(3,),
        ...                    strides=(2,)))
        >>> critic = SharedEncoderCritic(enc, action_dim=1, num_cells=[32])
        >>> critic(torch.zeros(5, 1, 10, 10), torch.zeros(5, 2), torch.zeros(5, 1)).shape
        torch.Size([5, 1])
        >>> critic.encoder is enc
        True
    """

    def __init__(self, encoder: nn.Module, action_dim: int, num_cells: list[int]) -> None:
        super().__init__()
        self.encoder = encoder
        self.body = stack_for_seeds(
            MLP(in_features=encoder.out_features + action_dim, out_features=1, num_cells=num_cells)
        )

    def head(self, features: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``Q`` from the encoder's ``features`` of ``s`` and the action."""
        return self.body(torch.cat([features, action], -1))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        *obs, action = inputs
        return self.head(self.encoder(*obs), action)


def _encoder(
    inputs: int | Sequence[Shape], fourier: int, cnn: ConvSpec | None
) -> tuple[nn.Module | None, int]:
    """The input encoder (``None``: raw concatenated vectors) and its number of features."""
    shapes = [(inputs,)] if isinstance(inputs, int) else [tuple(s) for s in inputs]
    if fourier <= 0 and all(len(s) == 1 for s in shapes):
        return None, sum(s[0] for s in shapes)
    encoder = InputEncoder(shapes, fourier=fourier, cnn=cnn)
    return encoder, encoder.out_features


def mlp(
    inputs: int | Sequence[Shape],
    out_features: int,
    num_cells: list[int],
    fourier: int = 0,
    cnn: ConvSpec | None = None,
) -> nn.Module:
    """An MLP over the inputs: ``inputs`` is a vector size, or the shape of each input (see
    :class:`InputEncoder`: images go through a CNN, vectors optionally through Fourier features).
    """
    encoder, width = _encoder(inputs, fourier, cnn)
    body = MLP(in_features=width, out_features=out_features, num_cells=num_cells)
    return stack_for_seeds(body if encoder is None else _Encoded(encoder, body))


def qvalue_net(
    inputs: int | Sequence[Shape],
    num_actions: int,
    num_cells: list[int],
    *,
    dueling: bool = False,
    fourier: int = 0,
    cnn: ConvSpec | None = None,
) -> nn.Module:
    """Q-values of every action: an MLP, or a dueling one (``Q = V + A - mean(A)``, the last
    hidden width feeding separate value and advantage heads). ``inputs`` as in :func:`mlp`."""
    if not dueling:
        return mlp(inputs, num_actions, num_cells, fourier, cnn)
    encoder, width_in = _encoder(inputs, fourier, cnn)
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
    return stack_for_seeds(net if encoder is None else _Encoded(encoder, net))
