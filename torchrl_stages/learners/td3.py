"""TD3 for continuous-action stages."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.objectives import TD3Loss
from torchrl.objectives.utils import distance_loss

from torchrl_stages.config.bounds import free, non_negative, positive
from torchrl_stages.learners.actor_critic import (
    DeterministicActorCriticConfig,
    DeterministicActorCriticLearner,
)
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.ops import td0_target


@dataclass
class TD3Config(DeterministicActorCriticConfig):
    """TD3 stage: twin critics, target policy smoothing and delayed actor updates."""

    algo: str = free("td3")
    policy_noise: float = non_negative(0.2)
    noise_clip: float = non_negative(0.5)
    policy_update_delay: int = positive(2)


@register_algorithm
class TD3Learner(DeterministicActorCriticLearner):
    """TD3 for one stage: parameters and targets in torchrl's ``TD3Loss``, the update on plain
    tensors.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> len(TD3Learner(TD3Config(), specs).value().critics)
        2
    """

    algo = "td3"
    Config = TD3Config
    torchrl_loss = TD3Loss
    update_draws_random = True  # the target policy's smoothing noise
    stacks_seeds = True

    def loss_kwargs(self, cfg: TD3Config) -> dict:
        noise = {"policy_noise": cfg.policy_noise, "noise_clip": cfg.noise_clip}
        return {**super().loss_kwargs(cfg), **noise, "delay_actor": True}

    def make_losses(self) -> None:
        self._value_loss = self.compiled(self._plain_value_loss)
        self._actor_loss = self.compiled(self._plain_actor_loss)

    def _plain_value_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """``TD3Loss.value_loss``: each critic against ``r + gamma min_i Q_i,target(s', a')``,
        ``a'`` with clipped noise (drawn first)."""
        cfg, action = self.cfg, batch.get(self.specs.action_key)
        noise = (torch.randn_like(action) * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
        low, high, _ = self._bounds
        with torch.no_grad():
            next_features = self.features(self.inputs(batch, nxt=True), target=True)
            next_action = self.squash(self.actor_head(next_features, target=True)) + noise
            next_action = torch.maximum(torch.minimum(next_action, high), low)
            targets = self.loss.target_qvalue_network_params
            next_q = self.critic_values(targets, next_features, next_action)
            target = td0_target(batch, torch.stack(next_q).min(0).values, cfg.gamma)
        features = self.features(self.inputs(batch))
        preds = self.critic_values(self.loss.qvalue_network_params, features, action)
        return sum(self.batch_mean(distance_loss(p, target, cfg.loss_function)) for p in preds)

    def _plain_actor_loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``-Q_1(s, mu(s))`` (critics and shared encoder detached) and the penalty."""
        with torch.no_grad():
            features = self.features(self.inputs(batch))
        u = self.actor_head(features)
        critics = self.loss.qvalue_network_params
        (q,) = self.critic_values(critics, features, self.squash(u), detach=True, count=1)
        return -self.batch_mean(q), self.penalty(u)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_q = self._value_loss(batch)
        out = self._optimize({"loss_qvalue": loss_q}, loss_q, "critic", targets=False)
        out["grad_norm_critic"] = self.grad_norms["critic"]
        if (self.num_updates + 1) % self.cfg.policy_update_delay == 0:
            loss_actor, penalty = self._actor_loss(batch)
            out |= self._optimize({"loss_actor": loss_actor}, loss_actor + penalty, "actor")
            out["grad_norm_actor"] = self.grad_norms["actor"]
        self.num_updates += 1
        return out
