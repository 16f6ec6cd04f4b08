"""DDPG for continuous-action stages: its config, learner and value."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch.func import functional_call
from torchrl.data import TensorSpec
from torchrl.objectives import DDPGLoss

from torchrl_stages.config.bounds import free
from torchrl_stages.learners.actor_critic import (
    DeterministicActorCriticConfig,
    DeterministicActorCriticLearner,
)
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.ops import detached_copy, distance, td0_target
from torchrl_stages.values import ActorCriticValue, with_params


@dataclass
class DDPGConfig(DeterministicActorCriticConfig):
    """DDPG stage (continuous, bounded actions): ``DDPGLoss``'s objective with Gaussian
    exploration."""

    algo: str = free("ddpg")


@register_algorithm
class DDPGLearner(DeterministicActorCriticLearner):
    """DDPG for one stage: its parameters (and their targets) in torchrl's ``DDPGLoss``, its
    update on :meth:`_plain_losses`, what that module computes on plain tensors.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> from torchrl_stages.learners.ddpg import DDPGConfig, DDPGLearner
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> learner = DDPGLearner(DDPGConfig(), specs)
        >>> sorted(learner.optimizers)
        ['actor', 'critic']
    """

    algo = "ddpg"
    Config = DDPGConfig
    CRITIC = "value_network"
    torchrl_loss = DDPGLoss
    stacks_seeds = True

    @classmethod
    def value_from_loss(cls, loss: DDPGLoss, live: bool = False) -> TensorDictModuleBase:
        """``Q_target(s, mu_target(s))`` of a ``DDPGLoss`` with target networks."""
        actor = with_params(loss.actor_network, loss.target_actor_network_params, live=live)
        critic = with_params(loss.value_network, loss.target_value_network_params, live=live)
        return ActorCriticValue(actor, [critic])

    def make_loss(self, cfg: DDPGConfig, spec: TensorSpec) -> DDPGLoss:
        loss = DDPGLoss(
            self.actor,
            self.critic,
            loss_function=cfg.loss_function,
            delay_actor=True,
            delay_value=True,
        )
        self.drop_critic_encoder_copies(loss, "value_network")
        return loss

    def make_losses(self) -> None:
        target_critic = self.with_target_encoder(self.loss.target_value_network_params)
        self.__dict__["_target_critic"] = with_params(
            self.critic_module, target_critic.get("module"), live=True
        )
        losses = self._shared_losses if self.shared_encoder else self._plain_losses
        self._losses = self.compiled(losses)

    def _plain_losses(
        self, batch: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | float]:
        """What ``DDPGLoss`` computes, on plain tensors: the actor loss ``-Q(s, mu(s))`` (the
        critic's parameters detached), the critic loss against ``r + gamma (1 - terminated)
        Q_target(s', mu_target(s'))``, and the saturation penalty."""
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        pred = self.critic_module(*obs, batch.get(self.specs.action_key))
        with torch.no_grad():
            next_value = self._target_critic(*next_obs, self.squash(self._target_actor(*next_obs)))
            target = td0_target(
                batch.get("next"),
                next_value,
                float(self.cfg.gamma),
                batch.get("steps_to_next_obs", None),
            )
        loss_value = self.batch_mean(distance(pred, target, self.cfg.loss_function))
        u = self.actor_module(*obs)
        detached = {n: p.detach() for n, p in self.critic_module.named_parameters()}
        q = functional_call(self.critic_module, detached, (*obs, self.squash(u)))
        return -self.batch_mean(q), loss_value, self.penalty(u)

    def _shared_losses(
        self, batch: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | float]:
        """:meth:`_plain_losses` with one encoder: ``s`` encoded once (the critic loss trains
        the encoder; the actor reads its features detached), ``s'`` once by the target one."""
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        features = self.actor_module.encoder(*obs)
        pred = self.critic_module.head(features, batch.get(self.specs.action_key))
        with torch.no_grad():
            next_features = self._target_actor.encoder(*next_obs)
            next_action = self.squash(self._target_actor.body(next_features))
            target = td0_target(
                batch.get("next"),
                self._target_critic.head(next_features, next_action),
                float(self.cfg.gamma),
                batch.get("steps_to_next_obs", None),
            )
        loss_value = self.batch_mean(distance(pred, target, self.cfg.loss_function))
        features = features.detach()
        u = self.actor_module.body(features)
        body = self.critic_module.body
        detached = {n: p.detach() for n, p in body.named_parameters()}
        q = functional_call(body, detached, (torch.cat([features, self.squash(u)], -1),))
        return -self.batch_mean(q), loss_value, self.penalty(u)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_actor, loss_value, penalty = self._losses(batch)
        self._check_losses(loss_actor=loss_actor, loss_value=loss_value)
        self._step(loss_actor + loss_value + penalty)
        self.target_updater.step()
        self.num_updates += 1
        return {
            "loss_actor": detached_copy(loss_actor),
            "loss_value": detached_copy(loss_value),
            "grad_norm_actor": self.grad_norms["actor"],
            "grad_norm_critic": self.grad_norms["critic"],
        }

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``Q_target(s, mu_target(s))``."""
        loss = self.loss
        critic = self.with_target_encoder(loss.target_value_network_params)
        return ActorCriticValue(
            with_params(self.actor, loss.target_actor_network_params, live=live),
            [with_params(self.critic, critic, live=live)],
        )
