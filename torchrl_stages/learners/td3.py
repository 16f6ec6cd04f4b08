"""TD3 stage learner (continuous, bounded actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorSpec
from torchrl.objectives import TD3Loss

from torchrl_stages.config import TD3Config
from torchrl_stages.learners.actor_critic import ActorCriticLearner
from torchrl_stages.values import ActorCriticValue, with_params


class TD3Learner(ActorCriticLearner):
    """TD3 for one stage, on torchrl's ``TD3Loss`` (twin critics, delayed actor updates).

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.config import TD3Config
        >>> from torchrl_stages.learners import StageSpecs, TD3Learner
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> learner = TD3Learner(TD3Config(), specs)
        >>> len(learner.value().critics)
        2
    """

    algo = "td3"

    def make_loss(self, cfg: TD3Config, spec: TensorSpec) -> TD3Loss:
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
        )
        loss.set_keys(action=self.specs.action_key)
        return loss

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        return (
            list(self.loss.actor_network_params.flatten_keys().values()),
            list(self.loss.qvalue_network_params.flatten_keys().values()),
        )

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_q, _ = self.loss.value_loss(batch)
        self._check_losses(loss_qvalue=loss_q)
        self._step(loss_q, "critic")
        out = {"loss_qvalue": loss_q.detach(), "grad_norm_critic": self.grad_norms["critic"]}
        if (self.num_updates + 1) % self.cfg.policy_update_delay == 0:
            (loss_actor, _), penalty = self.with_saturation_penalty(self.loss.actor_loss, batch)
            self._check_losses(loss_actor=loss_actor)
            self._step(loss_actor + penalty, "actor")
            self.optimizers["critic"].zero_grad(set_to_none=True)
            self.target_updater.step()
            out["loss_actor"] = loss_actor.detach()
            out["grad_norm_actor"] = self.grad_norms["actor"]
        self.num_updates += 1
        return out

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``min_i Q_i,target(s, mu_target(s))`` over the twin critics."""
        loss = self.loss
        critics = [
            with_params(self.critic, loss.target_qvalue_network_params[i], live=live)
            for i in range(loss.target_qvalue_network_params.shape[0])
        ]
        actor = with_params(self.actor, loss.target_actor_network_params, live=live)
        return ActorCriticValue(actor, critics)
