"""What every per-stage learner provides to the shared stage-training loop."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, Categorical, OneHot, TensorSpec

from torchrl_stages.config import StageChecks, StageConfig, as_dataclass
from torchrl_stages.learners.networks import ConvSpec
from torchrl_stages.learners.ops import (
    FusedAdam,
    clip_seed_grads,
    linear_schedule,
    seed_grad_norms,
    total_grad_norm,
)
from torchrl_stages.learners.stacking import current_rows, current_seeds, seed_axes


@dataclass
class StageSpecs:
    """The slice of an env a stage learner is built from.

    Attributes:
        observation_keys: the entries its networks read.
        observation_dim: the summed size of the vector entries (concatenated).
        action_key: the entry its policy writes.
        action_spec: the unbatched spec of that entry.
        observation_shapes: unbatched shape of each observation entry, ``(d,)`` for vectors and
            ``(C, H, W)`` for images (which go through a CNN); ``None``: all are vectors.
    """

    observation_keys: list[NestedKey]
    observation_dim: int
    action_key: NestedKey
    action_spec: TensorSpec
    observation_shapes: list[tuple[int, ...]] | None = None

    @property
    def input_shapes(self) -> list[tuple[int, ...]]:
        """The shapes network builders take (one flat vector unless shapes are given)."""
        if self.observation_shapes is None:
            return [(self.observation_dim,)]
        return [tuple(s) for s in self.observation_shapes]


def is_discrete(spec: TensorSpec) -> bool:
    return isinstance(spec, (Categorical, OneHot))


def is_continuous(spec: TensorSpec) -> bool:
    return isinstance(spec, Bounded) and spec.dtype.is_floating_point


class NonFiniteError(FloatingPointError):
    """A learner's loss, gradient or parameter is NaN or infinite (the stage diverged)."""

    def __init__(self, what: str, update: int) -> None:
        super().__init__(f"{what} is not finite at update {update}")
        self.what, self.update = what, update


LOSS_FUNCTIONS = ("l1", "l2", "smooth_l1")


def check_loss_function(checks: StageChecks) -> None:
    """A stage's ``loss_function`` is one :func:`distance` knows."""
    checks(
        checks.cfg["loss_function"] in LOSS_FUNCTIONS,
        "loss_function",
        f"unknown (known: {', '.join(LOSS_FUNCTIONS)})",
        f"set {checks.key}.loss_function=l2",
    )


ALGORITHMS: dict[str, type[Learner]] = {}


def register_algorithm(cls: type[Learner]) -> type[Learner]:
    """Class decorator: makes a :class:`Learner` subclass an algorithm known by its
    :attr:`Learner.algo` name to the CLI (``algo@task.stages.<stage>=<name>``), the config
    store, validation, the help text and the value adapters. Its :attr:`Learner.Config` is the
    schema of its stages' keys.

    Examples:
        >>> from dataclasses import dataclass
        >>> from torchrl_stages.config import StageConfig
        >>> @dataclass
        ... class NoopConfig(StageConfig):
        ...     algo: str = "noop"
        >>> @register_algorithm
        ... class Noop(Learner):
        ...     algo, Config = "noop", NoopConfig
        >>> ALGORITHMS.pop("noop") is Noop
        True
    """
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


def action_space_kind(spec: TensorSpec) -> str:
    """``"discrete"`` (Categorical, OneHot), ``"continuous"`` (bounded float) or the spec's
    class name."""
    if is_discrete(spec):
        return "discrete"
    if is_continuous(spec):
        return "continuous"
    return type(spec).__name__


class Learner(nn.Module, ABC):
    """One stage's algorithm: networks, exploration, loss, optimizers and target updater.

    An algorithm is one module of :mod:`torchrl_stages.learners`: a subclass that names itself
    (:attr:`algo`), declares its config dataclass (:attr:`Config`), the action spaces it
    accepts (:attr:`action_spaces`), its learning-rate keys (:attr:`lr_keys`) and its own
    validation (:meth:`validate`), builds its networks from a
    :class:`~torchrl_stages.config.StageConfig` and :class:`StageSpecs`, implements
    :meth:`update`, :meth:`anneal_exploration` and :meth:`value` (the ``V(s)`` it hands to the
    stage before it), and is registered with :func:`register_algorithm`. The loops in
    :mod:`torchrl_stages.stage` and :mod:`torchrl_stages.schedules.joint` only talk to this
    interface.

    Attributes:
        policy: the greedy (deterministic) policy, used for evaluation and the stacked policy.
        exploration_policy: the policy the collector runs (policy + exploration module).
        optimizers: named optimizers, saved with checkpoints.
    """

    #: the algorithm's name in configs (``algo: <name>``)
    algo: str = ""
    #: the schema of its stages' keys
    Config: type[StageConfig] = StageConfig
    #: the action spaces it acts in (:func:`action_space_kind`)
    action_spaces: tuple[str, ...] = ()
    #: its learning-rate keys (what a diverged stage's error message suggests lowering)
    lr_keys: tuple[str, ...] = ("lr",)
    #: the torchrl loss module whose target networks :meth:`value_from_loss` reads
    torchrl_loss: type | None = None
    #: whether :meth:`update` draws from torch's global generator (a target policy's smoothing
    #: noise); if not, the stage loop samples all of a batch's minibatches in one draw
    update_draws_random: bool = False
    #: whether it trains seed-stacked (:mod:`~torchrl_stages.learners.stacking`): every
    #: network from :mod:`~torchrl_stages.learners.networks` and every loss reduced with
    #: :meth:`batch_mean`
    stacks_seeds: bool = False

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
        #: seeds its networks are stacked for (``make_learner(..., seeds=N)``); ``None``: one
        self.seeds: int | None = current_seeds()

    def batch_mean(self, x: torch.Tensor) -> torch.Tensor:
        """The mean of a loss term over its batch: a scalar, or one per seed (``[N]``) for a
        seed-stacked learner, whose batches are ``[N, B, ...]`` (``[len(rows), B, ...]`` for
        the seeds of :func:`~torchrl_stages.learners.stacking.update_rows`)."""
        if self.seeds is None:
            return x.mean()
        rows = current_rows()
        return x.reshape(self.seeds if rows is None else rows.numel(), -1).mean(-1)

    @property
    def replay_keys(self) -> list[NestedKey]:
        """The entries of a transition its update reads, what a stage's replay buffer keeps:
        the observations, the action, and ``next``'s observations, reward, ``done`` and
        ``terminated``."""
        obs = list(self.specs.observation_keys)
        following = [("next", k) if isinstance(k, str) else ("next", *k) for k in obs]
        done = [("next", "reward"), ("next", "done"), ("next", "terminated")]
        return [*obs, self.specs.action_key, *following, *done]

    @property
    def device(self) -> torch.device:
        """Where the networks live (``make_learner``'s ``device``): replay batches go there."""
        return next(self.parameters()).device

    @property
    def cnn(self) -> ConvSpec:
        """The CNN applied to image observations, from ``cfg.cnn_*``."""
        cfg = self.cfg
        return ConvSpec(tuple(cfg.cnn_channels), tuple(cfg.cnn_kernels), tuple(cfg.cnn_strides))

    @classmethod
    def check_action_spec(cls, spec: TensorSpec) -> str | None:
        """Why this algorithm cannot act on ``spec`` (``None`` when it can)."""
        kind = action_space_kind(spec)
        if not cls.action_spaces or kind in cls.action_spaces:
            return None
        others = [name for name, c in ALGORITHMS.items() if kind in c.action_spaces]
        return (
            f"{cls.algo} needs a {' or '.join(cls.action_spaces)} action space, got "
            f"{type(spec).__name__}" + (f"; use algo {' or '.join(others)}" if others else "")
        )

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        """The algorithm's own checks of a stage's keys, beyond every stage's (raise
        :class:`~torchrl_stages.config.ConfigError` through ``checks``)."""

    @classmethod
    def value_from_loss(cls, loss: Any, live: bool = False) -> TensorDictModuleBase:
        """``V(s)`` from the target networks of a :attr:`torchrl_loss` of this algorithm (see
        :func:`torchrl_stages.loss_value.value_from_loss`)."""
        raise NotImplementedError(f"{cls.algo} has no value from a torchrl loss")

    @abstractmethod
    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on a replay batch, target update included; returns the losses
        (:func:`detached_copy`: detached copies)."""

    def inputs(self, batch: TensorDictBase, nxt: bool = False) -> list[torch.Tensor]:
        """The network inputs of a batch (of its ``"next"`` states with ``nxt``), in order."""
        td = batch.get("next") if nxt else batch
        return [td.get(key) for key in self.specs.observation_keys]

    def compiled(self, fn):
        """``fn`` (an update's loss function) through ``torch.compile`` unless
        :attr:`compile_mode` is ``"off"``; ``"reduce-overhead"`` uses CUDA graphs on a GPU."""
        if self.compile_mode == "off":
            return fn
        return torch.compile(fn, mode=None if self.compile_mode == "default" else self.compile_mode)

    def adam(self, params, lr: float) -> torch.optim.Adam:
        """Adam over ``params``, fused (:class:`FusedAdam`) when ``cfg.fused_adam``."""
        if self.cfg.fused_adam:
            return FusedAdam(params, lr=lr)
        return torch.optim.Adam(params, lr=lr)

    def anneal(self, frames: int) -> None:
        """Sets the schedules for ``frames`` collected frames: exploration noise and the
        learning rates (linear decay to ``cfg.lr_end_factor`` of their start over ``cfg.frames``).
        """
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
        """This stage's state-value module ``V(s)`` from its target networks.

        By default a copy of their current values (an env transform freezes it further, see
        :func:`torchrl_stages.transforms.freeze`); with ``live`` it reads the target networks
        themselves and follows their updates (the joint schedule's replay-buffer transforms).
        """

    def _check_losses(self, **losses: torch.Tensor) -> None:
        """Raises :class:`NonFiniteError` naming the first loss that is NaN or infinite."""
        for name, value in losses.items():
            if not bool(torch.isfinite(value).all()):
                raise NonFiniteError(name, self.num_updates + 1)

    def _step(self, loss: torch.Tensor, *names: str) -> None:
        """Backward ``loss`` and step the named optimizers (all when none are named).

        Each optimizer's gradient is clipped to ``cfg.max_grad_norm`` when set; its norm before
        clipping is kept in :attr:`grad_norms`, and a non-finite one raises
        :class:`NonFiniteError` before any parameter changes. A seed-stacked learner's ``loss``
        holds one loss per seed; each seed's gradient has its own norm and clipping.
        """
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
                norm = seed_grad_norms(grads, self.seeds, axes)
                if max_norm is not None:
                    clip_seed_grads(grads, float(max_norm), norm, axes)
            if not bool(torch.isfinite(norm).all()):
                raise NonFiniteError(f"the gradient of the {name} parameters", self.num_updates + 1)
            self.grad_norms[name] = norm.detach()
        for name in names:
            optimizer = self.optimizers[name]
            if isinstance(optimizer, FusedAdam):
                optimizer.direct_step()
            else:
                optimizer.step()
            optimizer.zero_grad(set_to_none=True)

    def _seed_axes_of(self, name: str, params: list[torch.Tensor]) -> list[int]:
        """The seeds' axis in each of ``params`` (optimizer ``name``'s) that has a gradient, in
        a seed-stacked learner; the axes are read once per optimizer."""
        cache = self.__dict__.setdefault("_optimizer_seed_axes", {})
        if name not in cache:
            names = {id(p): n for n, p in self.named_parameters(remove_duplicate=False)}
            axes = seed_axes(self)
            cache[name] = [axes.get(names.get(id(p), "")) for p in params]
        out = []
        for p, axis in zip(params, cache[name], strict=True):
            if p.grad is None:
                continue
            if axis is None:
                raise RuntimeError(
                    f"a trained parameter of shape {tuple(p.shape)} has no seeds' axis: "
                    f"{type(self).__name__} cannot train stacked seeds (stacks_seeds)"
                )
            out.append(axis)
        return out

    def check_finite(self) -> None:
        """Raises :class:`NonFiniteError` if a parameter or buffer (targets included) is NaN or
        infinite."""
        # one check over every tensor at once (the stage loop calls this after every batch);
        # the state_dict walk below only runs to name the culprit
        tensors = [
            t.reshape(-1) for t in (*self.parameters(), *self.buffers()) if t.is_floating_point()
        ]
        if not tensors or bool(torch.cat(tensors).isfinite().all()):
            return
        for name, tensor in self.state_dict().items():
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                raise NonFiniteError(f"parameter {name}", self.num_updates)

    def checkpoint(self) -> dict[str, Any]:
        """Weights (target networks included), exploration state and optimizer states."""
        return {
            "model": self.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "num_updates": self.num_updates,
        }

    def load_checkpoint(self, state: dict[str, Any]) -> None:
        self.load_state_dict(state["model"])
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(state["optimizers"][name])
        self.num_updates = int(state.get("num_updates", 0))
