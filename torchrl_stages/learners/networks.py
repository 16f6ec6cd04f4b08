"""Network builders of the learners, stacked for seeds inside :func:`.stacked_networks`."""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torchrl.modules import MLP
from torchrl.modules.models.models import DuelingMlpDQNet

from torchrl_stages.learners.stacking import stack_for_seeds


class FourierFeatures(nn.Module):
    """``x -> [x, sin(2^k pi x), cos(2^k pi x)]`` for ``k < num_octaves``: sharp changes of
    low-dimensional coordinates (a wall one grid cell away) for a small MLP.

    Examples:
        >>> FourierFeatures(2)(torch.zeros(3, 2)).shape
        torch.Size([3, 10])
    """

    def __init__(self, num_octaves: int) -> None:
        super().__init__()
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(num_octaves), persistent=False)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = torch.cat(inputs, -1)
        angles = (x.unsqueeze(-1) * self.freqs).flatten(-2)
        return torch.cat([x, angles.sin(), angles.cos()], -1)


Shape = tuple[int, ...]


@dataclass(frozen=True)
class ConvSpec:
    """The CNN of image inputs: per layer ``Conv2d(kernel, stride, padding=kernel // 2)`` + ReLU."""

    channels: tuple[int, ...] = (16, 32)
    kernels: tuple[int, ...] = (3, 3)
    strides: tuple[int, ...] = (1, 2)


class ConvEncoder(nn.Module):
    """A CNN over ``[*batch, C, H, W]`` images of any dtype, flattened to ``[*batch, features]``.

    Examples:
        >>> ConvEncoder((1, 10, 10), ConvSpec())(torch.zeros(4, 7, 1, 10, 10)).shape
        torch.Size([4, 7, 800])
    """

    def __init__(self, shape: Shape, spec: ConvSpec) -> None:
        super().__init__()
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
    """CNN features of each image input ``(C, H, W)``, then the vector inputs ``(d,)`` (through
    :class:`FourierFeatures` when ``fourier > 0``); ``inputs``: their shapes in call order.

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
        vector_features = vector_dim * (1 + 2 * fourier) if self.fourier else vector_dim
        self.out_features = sum(conv.out_features for conv in self.convs) + vector_features

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        images = iter(self.convs)
        features = [next(images)(x) for x, img in zip(inputs, self.is_image, strict=True) if img]
        vectors = [x for x, img in zip(inputs, self.is_image, strict=True) if not img]
        if vectors:
            features.append(self.fourier(*vectors) if self.fourier else torch.cat(vectors, -1))
        return torch.cat(features, -1)


class Chain(nn.Sequential):
    """``nn.Sequential`` whose first module takes several inputs (e.g. an image and a vector);
    an ``OrderedDict`` names its modules (:func:`mlp`'s ``encoder`` and ``body``).

    Examples:
        >>> net = Chain(InputEncoder([(2,), (1,)]), nn.Linear(3, 1))
        >>> net(torch.ones(4, 2), torch.ones(4, 1)).shape
        torch.Size([4, 1])
    """

    def forward(self, *inputs: torch.Tensor):
        first, *rest = self
        out = first(*inputs)
        for module in rest:
            out = module(out)
        return out


class SharedEncoderCritic(Chain):
    """``Q(s, a) = body([encoder(s), a])`` over the actor's own input encoder.

    Examples:
        >>> critic = SharedEncoderCritic(InputEncoder([(2,)], fourier=1), 1, num_cells=[32])
        >>> critic(torch.zeros(5, 2), torch.zeros(5, 1)).shape
        torch.Size([5, 1])
    """

    def __init__(self, encoder: nn.Module, action_dim: int, num_cells: list[int]) -> None:
        width = encoder.out_features + action_dim
        body = MLP(in_features=width, out_features=1, num_cells=num_cells)
        super().__init__(OrderedDict(encoder=encoder, body=stack_for_seeds(body)))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        *obs, action = inputs
        return self.body(torch.cat([self.encoder(*obs), action], -1))


def mlp(
    inputs: int | Sequence[Shape],
    out_features: int,
    num_cells: list[int],
    fourier: int = 0,
    cnn: ConvSpec | None = None,
    *,
    dueling: bool = False,
) -> nn.Module:
    """An MLP over ``inputs``, a vector size or each input's shape (:class:`InputEncoder`);
    ``dueling``: ``Q = V + A - mean(A)``, the last hidden width feeding the two heads."""
    shapes = [(inputs,)] if isinstance(inputs, int) else [tuple(s) for s in inputs]
    encoder = None
    if fourier > 0 or any(len(s) != 1 for s in shapes):
        encoder = InputEncoder(shapes, fourier=fourier, cnn=cnn)
    width = sum(s[0] for s in shapes) if encoder is None else encoder.out_features
    if not dueling:
        net = MLP(in_features=width, out_features=out_features, num_cells=num_cells)
    else:
        *trunk, hidden = num_cells
        relu = {"activation_class": nn.ReLU}  # torchrl's default: ELU
        features = dict(in_features=width, num_cells=trunk, out_features=hidden, **relu)
        heads = dict(in_features=hidden, num_cells=hidden, **relu)  # one hidden layer each
        net = DuelingMlpDQNet(out_features, mlp_kwargs_feature=features, mlp_kwargs_output=heads)
    if encoder is not None:
        net = Chain(OrderedDict(encoder=encoder, body=net))
    return stack_for_seeds(net)
