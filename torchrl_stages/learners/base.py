"""The learner interface: what every per-stage learner provides to the stage-training loops."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot, TensorSpec
from torchrl.objectives import LossModule, ValueEstimators

from torchrl_stages.config import StageChecks, StageConfig, as_dataclass
from torchrl_stages.learners.networks import ConvSpec, mlp
from torchrl_stages.learners.ops import (
    FusedAdam,
    FusedSoftUpdate,
    clip_seed_grads,
    linear_schedule,
    total_grad_norm,
)
from torchrl_stages.learners.stacking import current_rows, current_seeds, seed_axes


@dataclass
class StageSpecs:
    """The slice of an env a stage learner is built from: ``observation_dim`` sums the vector
    entries; ``observation_shapes`` holds each entry's ``(d,)`` or ``(C, H, W)`` (``None``: all
    vectors)."""

    observation_keys: list[NestedKey]
    observation_dim: int
    action_key: NestedKey
    action_spec: TensorSpec
    observation_shapes: list[tuple[int, ...]] | None = None

    @property
    def input_shapes(self) -> list[tuple[int, ...]]:
        if self.observation_shapes is None:
            return [(self.observation_dim,)]
        return [tuple(s) for s in self.observation_shapes]


class NonFiniteError(FloatingPointError):
    """A loss, gradient or parameter is NaN or infinite (the stage diverged)."""

    def __init__(self, what: str, update: int) -> None:
        super().__init__(f"{what} is not finite at update {update}")
        self.what, self.update = what, update


LOSS_FUNCTIONS = ("l1", "l2", "smooth_l1")


#: every algorithm by its name in configs, filled by :func:`register_algorithm`
ALGORITHMS: dict[str, type[Learner]] = {}


def register_algorithm(cls: type[Learner]) -> type[Learner]:
    """Class decorator: makes ``cls`` the algorithm ``cls.algo`` of configs and the CLI."""
    name = cls.algo
    if not name or not isinstance(cls.Config, type) or cls.Config.algo != name:
        raise TypeError(
            f"{cls.__name__}: an algorithm needs a name (algo) and a Config dataclass whose "
            f"algo field defaults to it, got algo={name!r}, Config={cls.Config!r}"
        )
    if ALGORITHMS.get(name, cls) is not cls:
        raise ValueError(f"algorithm {name!r} is registered twice ({ALGORITHMS[name]}, {cls})")
    ALGORITHMS[name] = cls
    return cls


class Learner(nn.Module, ABC):
    """One stage's algorithm: networks, exploration, loss, optimizers and target updater.

    A subclass sets the class attributes below and ``policy`` (greedy), ``exploration_policy``
    and ``optimizers`` (saved with checkpoints); it implements :meth:`update`,
    :meth:`anneal_exploration` and :meth:`value`.
    """

    algo: str = ""  #: the algorithm's name in configs
    Config: type[StageConfig] = StageConfig  #: the schema of its stages' keys
    action_spaces: tuple[str, ...] = ()  #: "discrete" and/or "continuous"
    lr_keys: tuple[str, ...] = ("lr",)  #: what a diverged stage's message suggests lowering
    torchrl_loss: type | None = None  #: the loss module :meth:`value_from_loss` reads
    #: whether :meth:`update` draws random numbers (else a batch's minibatches are drawn at once)
    update_draws_random: bool = False
    stacks_seeds: bool = False  #: networks from :mod:`.networks`, losses :meth:`batch_mean`

    def __init__(self, cfg: StageConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__()
        self.cfg = as_dataclass(cfg)  # plain reads in the update's hot path
        self.specs = specs
        self.compile_mode = compile  # off | default | reduce-overhead | max-autotune
        self.policy: TensorDictModuleBase
        self.exploration_policy: TensorDictModuleBase
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.grad_norms: dict[str, torch.Tensor] = {}  # of the last update, per optimizer
        self.num_updates = 0
        self.seeds: int | None = current_seeds()  # seeds its networks stack; None: one
        #: the seed-stacked learner this one was trained in, and its row (a stage's value for
        #: several seeds is then read from it, not stacked anew)
        self.stacked_row: tuple[Learner, int] | None = None

    def batch_mean(self, x: torch.Tensor) -> torch.Tensor:
        """The mean over the batch: a scalar, or one per seed (``[N]``) when seed-stacked."""
        if self.seeds is None:
            return x.mean()
        rows = current_rows()
        return x.reshape(self.seeds if rows is None else rows.numel(), -1).mean(-1)

    @property
    def replay_keys(self) -> list[NestedKey]:
        """The entries of a transition its update reads (what the replay buffer keeps)."""
        obs = list(self.specs.observation_keys)
        following = [unravel_key(("next", k)) for k in [*obs, "reward", "done", "terminated"]]
        return [*obs, self.specs.action_key, *following]

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def network(self, out_features: int, *extra_inputs: tuple[int, ...], dueling: bool = False):
        """A network from the observations and ``extra_inputs`` to ``out_features`` (``cfg``'s
        ``num_cells``, ``fourier_features`` and ``cnn_*``)."""
        cfg, inputs = self.cfg, [*self.specs.input_shapes, *extra_inputs]
        cnn = ConvSpec(tuple(cfg.cnn_channels), tuple(cfg.cnn_kernels), tuple(cfg.cnn_strides))
        return mlp(
            inputs, out_features, list(cfg.num_cells), cfg.fourier_features, cnn, dueling=dueling
        )

    def exploration_module(self, module: type[nn.Module], start: float, end: float) -> nn.Module:
        """torchrl's exploration ``module`` (``EGreedyModule``, ``AdditiveGaussianModule``), its
        noise ``start`` annealed to ``end`` over ``cfg.annealing_frames`` (:meth:`anneal_noise`)."""
        steps = max(int(self.cfg.annealing_frames), 1)
        spec, key = self.specs.action_spec, self.specs.action_key
        return module(spec, float(start), float(end), steps, action_key=key)

    def anneal_noise(self, noise: torch.Tensor, start: float, end: float, frames: int) -> None:
        """Sets an exploration module's ``noise`` for ``frames`` collected frames."""
        noise.fill_(linear_schedule(start, end, frames, self.cfg.annealing_frames))

    @classmethod
    def check_action_spec(cls, spec: TensorSpec) -> str | None:
        """Why this algorithm cannot act on ``spec`` (``None`` when it can)."""
        kind = type(spec).__name__
        if isinstance(spec, (Categorical, OneHot)):
            kind = "discrete"
        elif isinstance(spec, Bounded) and spec.dtype.is_floating_point:
            kind = "continuous"
        if not cls.action_spaces or kind in cls.action_spaces:
            return None
        needs = " or ".join(cls.action_spaces)
        others = [name for name, c in ALGORITHMS.items() if kind in c.action_spaces]
        hint = f"; use algo {' or '.join(others)}" if others else ""
        return f"{cls.algo} needs a {needs} action space, got {type(spec).__name__}{hint}"

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        """The algorithm's checks relating a stage's keys (each key's bound is checked first)."""

    @classmethod
    def value_from_loss(cls, loss: Any, live: bool = False) -> TensorDictModuleBase:
        """``V(s)`` from the target networks of a :attr:`torchrl_loss`."""
        raise NotImplementedError(f"{cls.algo} has no value from a torchrl loss")

    @abstractmethod
    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on a replay batch, target update included; the detached losses."""

    def use_loss(self, loss: LossModule) -> None:
        """Makes the torchrl ``loss`` the learner's: the stage's action key, TD(0) estimates at
        ``cfg.gamma`` and a :class:`.FusedSoftUpdate` of its targets by ``cfg.tau``."""
        if hasattr(loss.tensor_keys, "action"):
            loss.set_keys(action=self.specs.action_key)
        loss.make_value_estimator(ValueEstimators.TD0, gamma=self.cfg.gamma)
        self.loss = loss
        self.target_updater = FusedSoftUpdate(loss, tau=self.cfg.tau)

    def inputs(self, batch: TensorDictBase, nxt: bool = False) -> list[torch.Tensor]:
        """The network inputs of a batch (of its ``"next"`` states with ``nxt``)."""
        td = batch.get("next") if nxt else batch
        return [td.get(key) for key in self.specs.observation_keys]

    def compiled(self, fn):
        if self.compile_mode == "off":
            return fn
        return torch.compile(fn, mode=None if self.compile_mode == "default" else self.compile_mode)

    def adam(self, params, lr: float) -> torch.optim.Adam:
        """Adam, its fused kernel called directly with ``cfg.fused_adam`` (:class:`.FusedAdam`)."""
        return FusedAdam(params, lr=lr) if self.cfg.fused_adam else torch.optim.Adam(params, lr=lr)

    def anneal(self, frames: int) -> None:
        """Sets exploration and learning rates (linear to ``cfg.lr_end_factor`` of their start
        over ``cfg.frames``) for ``frames`` collected frames."""
        factor = linear_schedule(1.0, float(self.cfg.lr_end_factor), frames, int(self.cfg.frames))
        for optimizer in self.optimizers.values():
            for group in optimizer.param_groups:
                group["lr"] = group.setdefault("initial_lr", group["lr"]) * factor
        self.anneal_exploration(frames)

    @abstractmethod
    def anneal_exploration(self, frames: int) -> None:
        """Sets the exploration noise for ``frames`` collected frames."""

    @abstractmethod
    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``V(s)`` from the target networks: a copy, or with ``live`` the networks themselves
        (the joint schedule)."""

    def _check_losses(self, **losses: torch.Tensor) -> None:
        """Raises :class:`NonFiniteError` naming the first loss that is NaN or infinite."""
        for name, value in losses.items():
            if not bool(torch.isfinite(value).all()):
                raise NonFiniteError(name, self.num_updates + 1)

    def _optimize(self, losses: dict[str, torch.Tensor], total, *names: str, targets=True) -> dict:
        """Checks ``losses``, steps ``total`` and, with ``targets``, the target networks."""
        self._check_losses(**losses)
        self._step(total, *names)
        if targets:
            self.target_updater.step()
        # copies: under reduce-overhead a loss is a CUDA graph output its next replay overwrites
        return {name: loss.detach().clone() for name, loss in losses.items()}

    def _step(self, loss: torch.Tensor, *names: str) -> None:
        """Backward ``loss`` and step the named optimizers (all when none are named), each
        gradient (each seed's) clipped to ``cfg.max_grad_norm``; a non-finite gradient norm
        raises :class:`NonFiniteError` before any parameter changes."""
        names = names or tuple(self.optimizers)
        max_norm = self.cfg.max_grad_norm
        (loss.sum() if self.seeds is not None else loss).backward()
        for name in names:
            params = [p for group in self.optimizers[name].param_groups for p in group["params"]]
            grads = [p.grad for p in params if p.grad is not None]
            if self.seeds is None:
                norm = total_grad_norm(grads)
                if max_norm is not None:
                    torch.nn.utils.clip_grads_with_norm_(params, float(max_norm), norm)
            else:
                axes = self._seed_axes_of(name, params)
                norm = clip_seed_grads(grads, self.seeds, axes, max_norm)
            if not bool(torch.isfinite(norm).all()):
                raise NonFiniteError(f"the gradient of the {name} parameters", self.num_updates + 1)
            self.grad_norms[name] = norm.detach()
        for name in names:
            optimizer = self.optimizers[name]
            getattr(optimizer, "direct_step", optimizer.step)()
            optimizer.zero_grad(set_to_none=True)

    def _seed_axes_of(self, name: str, params: list[torch.Tensor]) -> list[int]:
        """The seeds' axis of each of optimizer ``name``'s ``params`` that has a gradient."""
        cache = self.__dict__.setdefault("_optimizer_seed_axes", {})
        if name not in cache:
            names = {id(p): n for n, p in self.named_parameters(remove_duplicate=False)}
            axes = seed_axes(self)
            cache[name] = [axes.get(names.get(id(p), "")) for p in params]
        axes = [axis for p, axis in zip(params, cache[name], strict=True) if p.grad is not None]
        if None in axes:
            raise RuntimeError(
                f"{type(self).__name__}: a trained parameter has no seeds' axis, so it cannot "
                "train stacked seeds (set stacks_seeds=False)"
            )
        return axes

    def check_finite(self) -> None:
        """Raises :class:`NonFiniteError` if a parameter or buffer is NaN or infinite."""
        # one check over every tensor at once; the walk only names the culprit
        every = (*self.parameters(), *self.buffers())
        tensors = [t.reshape(-1) for t in every if t.is_floating_point()]
        if not tensors or bool(torch.cat(tensors).isfinite().all()):
            return
        for name, tensor in self.state_dict().items():
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                raise NonFiniteError(f"parameter {name}", self.num_updates)

    def checkpoint(self) -> dict[str, Any]:
        """Weights (target networks included), exploration state and optimizer states."""
        optimizers = {k: o.state_dict() for k, o in self.optimizers.items()}
        return {
            "model": self.state_dict(),
            "optimizers": optimizers,
            "num_updates": self.num_updates,
        }

    def load_checkpoint(self, state: dict[str, Any]) -> None:
        self.load_state_dict(state["model"])
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state["optimizers"][name])
        self.num_updates = int(state.get("num_updates", 0))
