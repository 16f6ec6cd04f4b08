"""Pieces shared by the deterministic actor-critic learners (DDPG, TD3)."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import TensorSpec
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import LossModule, SoftUpdate, ValueEstimators

from torchrl_stages.config import DDPGConfig
from torchrl_stages.learners.base import Learner, StageSpecs, is_continuous, linear_schedule
from torchrl_stages.learners.networks import mlp


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
        self.actor = TensorDictSequential(
            TensorDictModule(
                mlp(specs.observation_dim, action_dim, list(cfg.num_cells), cfg.fourier_features),
                in_keys=specs.observation_keys,
                out_keys=["_actor_param"],
            ),
            TanhModule(in_keys=["_actor_param"], out_keys=[specs.action_key], spec=spec),
        )
        self.critic = ValueOperator(
            mlp(specs.observation_dim + action_dim, 1, list(cfg.num_cells), cfg.fourier_features),
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

    def anneal(self, frames: int) -> None:
        cfg = self.cfg
        self.noise.sigma.fill_(
            linear_schedule(cfg.sigma_init, cfg.sigma_end, frames, cfg.annealing_frames)
        )
