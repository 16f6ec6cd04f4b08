"""TD3 for continuous-action stages: its config, learner, checks and value."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorSpec
from torchrl.objectives import TD3Loss

from torchrl_stages.config import StageChecks
from torchrl_stages.config.bounds import free, non_negative, positive
from torchrl_stages.learners.actor_critic import (
    DeterministicActorCriticConfig,
    DeterministicActorCriticLearner,
)
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.ops import detached_copy, distance, td0_target
from torchrl_stages.values import ActorCriticValue, with_params


@dataclass
class TD3Config(DeterministicActorCriticConfig):
    """TD3 stage: twin critics, target policy smoothing and delayed actor updates."""

    algo: str = free("td3")
    policy_noise: float = non_negative(0.2)
    noise_clip: float = non_negative(0.5)
    policy_update_delay: int = positive(2)


@register_algorithm
class TD3Learner(DeterministicActorCriticLearner):
    """TD3 for one stage (twin critics, delayed actor updates): its parameters (and their
    targets) in torchrl's ``TD3Loss``, its update on what that module computes, on plain tensors.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> from torchrl_stages.learners.td3 import TD3Config, TD3Learner
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> learner = TD3Learner(TD3Config(), specs)
        >>> len(learner.value().critics)
        2
    """

    algo = "td3"
    Config = TD3Config
    torchrl_loss = TD3Loss
    update_draws_random = True  # the target policy's smoothing noise
    stacks_seeds = True

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        super().validate(checks)
        checks.positive("policy_update_delay", 2)
        checks.non_negative("policy_noise")
        checks.non_negative("noise_clip")

    @classmethod
    def value_from_loss(cls, loss: TD3Loss, live: bool = False) -> TensorDictModuleBase:
        """The minimum of a ``TD3Loss``'s twin target critics at ``mu_target(s)``."""
        params = loss.target_qvalue_network_params
        critics = [
            with_params(loss.qvalue_network, params[i], live=live) for i in range(params.shape[0])
        ]
        actor = with_params(loss.actor_network, loss.target_actor_network_params, live=live)
        return ActorCriticValue(actor, critics)

    def make_loss(self, cfg: TD3Config, spec: TensorSpec) -> TD3Loss:
        # separate_losses: a shared encoder's copies in the critics are views of the actor's,
        # not freshly sampled (drop_critic_encoder_copies then removes them)
        loss = TD3Loss(
            self.actor,
            self.critic,
            action_spec=spec,
            num_qvalue_nets=2,
            policy_noise=cfg.policy_noise,
            noise_clip=cfg.noise_clip,
            loss_function=cfg.loss_function,
            delay_actor=True,
            delay_qvalue=True,
            separate_losses=self.shared_encoder,
        )
        return self.with_action_key(loss)

    def make_losses(self) -> None:
        if self.shared_encoder:
            self._value_loss = self.compiled(self._shared_value_loss)
            self._actor_loss = self.compiled(self._shared_actor_loss)
        else:
            self._value_loss = self.compiled(self._plain_value_loss)
            self._actor_loss = self.compiled(self._plain_actor_loss)

    def _plain_value_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """What ``TD3Loss.value_loss`` computes, on plain tensors: every critic against
        ``r + gamma (1 - terminated) min_i Q_i,target(s', a')``, ``a'`` the target actor's
        action plus clipped Gaussian noise (drawn first, as torchrl does), summed."""
        cfg, action = self.cfg, batch.get(self.specs.action_key)
        noise = (torch.randn_like(action) * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        low, high, _ = self._bounds
        with torch.no_grad():
            next_action = self.squash(self._target_actor(*next_obs)) + noise
            next_action = torch.maximum(torch.minimum(next_action, high), low)
            targets = self.critic_values(
                self.loss.target_qvalue_network_params["module"], *next_obs, next_action
            )
            target = td0_target(
                batch.get("next"),
                torch.stack(targets).min(0).values,
                float(cfg.gamma),
                batch.get("steps_to_next_obs", None),
            )
        preds = self.critic_values(self.loss.qvalue_network_params["module"], *obs, action)
        return sum(self.batch_mean(distance(p, target, cfg.loss_function)) for p in preds)

    def _plain_actor_loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """``-Q_1(s, mu(s))`` with the critics' parameters detached, and the penalty."""
        obs = self.inputs(batch)
        u = self.actor_module(*obs)
        first = self.loss.qvalue_network_params["module"].detach()[:1]
        (q,) = self.critic_values(first, *obs, self.squash(u))
        return -self.batch_mean(q), self.penalty(u)

    def _shared_value_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """:meth:`_plain_value_loss` with one encoder: ``s'`` is encoded once, by the target
        encoder (the target actor's), for the target actor and both target critics; ``s`` once,
        by the trained encoder, whose gradient comes from both critics' losses."""
        cfg, action = self.cfg, batch.get(self.specs.action_key)
        noise = (torch.randn_like(action) * cfg.policy_noise).clamp(-cfg.noise_clip, cfg.noise_clip)
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        low, high, _ = self._bounds
        with torch.no_grad():
            features = self._target_actor.encoder(*next_obs)
            next_action = self.squash(self._target_actor.body(features)) + noise
            next_action = torch.maximum(torch.minimum(next_action, high), low)
            targets = self.head_values(
                self.loss.target_qvalue_network_params["module", "body"], features, next_action
            )
            target = td0_target(
                batch.get("next"),
                torch.stack(targets).min(0).values,
                float(cfg.gamma),
                batch.get("steps_to_next_obs", None),
            )
        features = self.actor_module.encoder(*obs)
        preds = self.head_values(
            self.loss.qvalue_network_params["module", "body"], features, action
        )
        return sum(self.batch_mean(distance(p, target, cfg.loss_function)) for p in preds)

    def _shared_actor_loss(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_plain_actor_loss` on the shared encoder's features of ``s``, detached: the
        actor loss trains the actor's head only."""
        with torch.no_grad():
            features = self.actor_module.encoder(*self.inputs(batch))
        u = self.actor_module.body(features)
        first = self.loss.qvalue_network_params["module", "body"].detach()[:1]
        (q,) = self.head_values(first, features, self.squash(u))
        return -self.batch_mean(q), self.penalty(u)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_q = self._value_loss(batch)
        self._check_losses(loss_qvalue=loss_q)
        self._step(loss_q, "critic")
        out = {"loss_qvalue": detached_copy(loss_q), "grad_norm_critic": self.grad_norms["critic"]}
        if (self.num_updates + 1) % self.cfg.policy_update_delay == 0:
            loss_actor, penalty = self._actor_loss(batch)
            self._check_losses(loss_actor=loss_actor)
            self._step(loss_actor + penalty, "actor")
            self.optimizers["critic"].zero_grad(set_to_none=True)
            self.target_updater.step()
            out["loss_actor"] = detached_copy(loss_actor)
            out["grad_norm_actor"] = self.grad_norms["actor"]
        self.num_updates += 1
        return out

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``min_i Q_i,target(s, mu_target(s))`` over the twin critics."""
        loss = self.loss
        critics = self.with_target_encoder(loss.target_qvalue_network_params)
        critics = [with_params(self.critic, critics[i], live=live) for i in range(len(critics))]
        actor = with_params(self.actor, loss.target_actor_network_params, live=live)
        return ActorCriticValue(actor, critics)
