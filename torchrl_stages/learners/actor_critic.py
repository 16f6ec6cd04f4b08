"""Pieces shared by the deterministic actor-critic learners (DDPG, TD3)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import TensorSpec
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import LossModule, SoftUpdate, ValueEstimators

from torchrl_stages.config import DDPGConfig
from torchrl_stages.learners.base import Learner, StageSpecs, is_continuous, linear_schedule
from torchrl_stages.learners.networks import mlp

T = TypeVar("T")
SATURATION = 2.0  # pre-tanh magnitude beyond which `saturation_penalty` applies (tanh(2) = 0.96)


class ActorCriticLearner(Learner):
    """Deterministic actor + Q critic with Gaussian exploration; subclasses pick the loss.

    Subclasses implement :meth:`make_loss` and :meth:`update`; this class builds the actor
    (MLP + tanh squashing into the action bounds), the critic ``Q(s, a)``, the exploration
    module, the value estimator, the optimizers and the soft target updater.
    """

    def __init__(self, cfg: DDPGConfig, specs: StageSpecs) -> None:
        super().__init__(cfg, specs)
        spec = specs.action_spec
        action_dim = spec.shape[-1]
        inputs, cells, fourier = specs.input_shapes, list(cfg.num_cells), cfg.fourier_features
        self.actor = TensorDictSequential(
            TensorDictModule(
                mlp(inputs, action_dim, cells, fourier, self.cnn),
                in_keys=specs.observation_keys,
                out_keys=["_actor_param"],
            ),
            TanhModule(in_keys=["_actor_param"], out_keys=[specs.action_key], spec=spec),
        )
        self.critic = ValueOperator(
            mlp([*inputs, (action_dim,)], 1, cells, fourier, self.cnn),
            in_keys=[*specs.observation_keys, specs.action_key],
            out_keys=["state_action_value"],
        )
        self.noise = AdditiveGaussianModule(
            spec,
            sigma_init=float(cfg.sigma_init),
            sigma_end=float(cfg.sigma_end),
            annealing_num_steps=max(int(cfg.annealing_frames), 1),
            action_key=specs.action_key,
        )
        self.policy = self.actor
        self.exploration_policy = TensorDictSequential(self.actor, self.noise)
        self.loss = self.make_loss(cfg, spec)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = SoftUpdate(self.loss, tau=cfg.tau)
        actor_params, critic_params = self.loss_parameters()
        self.optimizers = {
            "actor": torch.optim.Adam(actor_params, lr=cfg.actor_lr),
            "critic": torch.optim.Adam(critic_params, lr=cfg.lr),
        }

    @classmethod
    def check_action_spec(cls, spec: TensorSpec) -> str | None:
        if not is_continuous(spec):
            return (
                f"{cls.algo.upper()} needs a bounded continuous action space (Bounded float), "
                f"got {type(spec).__name__}; use algo dqn for this stage"
            )
        return None

    def make_loss(self, cfg: DDPGConfig, spec: TensorSpec) -> LossModule:
        raise NotImplementedError

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The loss module's trainable (actor, critic) parameters."""
        raise NotImplementedError

    def with_saturation_penalty(
        self, loss_fn: Callable[[TensorDictBase], T], batch: TensorDictBase
    ) -> tuple[T, torch.Tensor | float]:
        """``loss_fn(batch)`` and ``cfg.saturation_penalty`` times the mean of
        ``relu(|u| - SATURATION)^2`` over the pre-tanh outputs ``u`` of the trained actor in it.

        Without the penalty an actor can drive ``u`` deep into tanh saturation, where its gradient
        vanishes and the policy stays at an action bound for good (e.g. a robot that only turns
        one way). Inside ``|u| <= SATURATION`` (``|action| <= 0.96`` of the bound) it is zero.
        """
        if self.cfg.saturation_penalty <= 0:
            return loss_fn(batch), 0.0
        captured: list[torch.Tensor] = []

        def keep(module, args, out) -> None:
            if out.get("_actor_param").requires_grad:  # the trained actor, not the target one
                captured.append(out.get("_actor_param"))

        handle = self.actor[0].register_forward_hook(keep)
        try:
            out = loss_fn(batch)
        finally:
            handle.remove()
        excess = (captured[-1].abs() - SATURATION).clamp_min(0.0)
        return out, self.cfg.saturation_penalty * excess.pow(2).mean()

    def anneal_exploration(self, frames: int) -> None:
        cfg = self.cfg
        self.noise.sigma.fill_(
            linear_schedule(cfg.sigma_init, cfg.sigma_end, frames, cfg.annealing_frames)
        )
