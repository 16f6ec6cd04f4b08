"""DDPG for continuous-action stages."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.objectives import DDPGLoss
from torchrl.objectives.utils import distance_loss

from torchrl_stages.config.bounds import free
from torchrl_stages.learners.actor_critic import (
    DeterministicActorCriticConfig,
    DeterministicActorCriticLearner,
)
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.ops import td0_target
from torchrl_stages.values import with_params


@dataclass
class DDPGConfig(DeterministicActorCriticConfig):
    """DDPG stage (continuous, bounded actions) with Gaussian exploration."""

    algo: str = free("ddpg")


@register_algorithm
class DDPGLearner(DeterministicActorCriticLearner):
    """DDPG for one stage: parameters and targets in torchrl's ``DDPGLoss``, the update on
    plain tensors.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> sorted(DDPGLearner(DDPGConfig(), specs).optimizers)
        ['actor', 'critic']
    """

    algo = "ddpg"
    Config = DDPGConfig
    CRITIC = "value_network"
    torchrl_loss = DDPGLoss
    stacks_seeds = True

    def loss_kwargs(self, cfg: DDPGConfig) -> dict:
        return {"delay_actor": True, "delay_value": True}

    def make_losses(self) -> None:
        targets = self.loss.target_value_network_params["module"]
        targets = targets["body"] if self.shared_encoder else targets
        self.__dict__["_target_critic"] = with_params(self.critic_net, targets, live=True)
        super().make_losses()

    def _plain_losses(self, batch: TensorDictBase):
        """``DDPGLoss``: the actor's ``-Q(s, mu(s))`` (critic and shared encoder detached), the
        critic's loss and the saturation penalty."""
        features = self.features(self.inputs(batch))
        pred = self.critic_net(*self.critic_inputs(features, batch.get(self.specs.action_key)))
        with torch.no_grad():
            next_features = self.features(self.inputs(batch, nxt=True), target=True)
            next_action = self.squash(self.actor_head(next_features, target=True))
            next_value = self._target_critic(*self.critic_inputs(next_features, next_action))
            target = td0_target(batch, next_value, self.cfg.gamma)
        loss_value = self.batch_mean(distance_loss(pred, target, self.cfg.loss_function))
        features = [f.detach() for f in features]
        u = self.actor_head(features)
        critic = self.loss.value_network_params
        (q,) = self.critic_values(critic, features, self.squash(u), detach=True)
        return -self.batch_mean(q), loss_value, self.penalty(u)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_actor, loss_value, penalty = self._losses(batch)
        losses = {"loss_actor": loss_actor, "loss_value": loss_value}
        out = self._optimize(losses, loss_actor + loss_value + penalty)
        self.num_updates += 1
        norms = self.grad_norms
        return {**out, "grad_norm_actor": norms["actor"], "grad_norm_critic": norms["critic"]}
