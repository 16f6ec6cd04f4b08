"""DDPG stage learner (continuous, bounded actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch.func import functional_call
from torchrl.data import TensorSpec
from torchrl.objectives import DDPGLoss

from torchrl_stages.config import DDPGConfig
from torchrl_stages.learners.actor_critic import ActorCriticLearner
from torchrl_stages.learners.base import distance, td0_target
from torchrl_stages.values import ActorCriticValue, with_params


class DDPGLearner(ActorCriticLearner):
    """DDPG for one stage, on torchrl's ``DDPGLoss`` (target actor and critic).

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.config import DDPGConfig
        >>> from torchrl_stages.learners import DDPGLearner, StageSpecs
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> learner = DDPGLearner(DDPGConfig(), specs)
        >>> sorted(learner.optimizers)
        ['actor', 'critic']
    """

    algo = "ddpg"

    def make_loss(self, cfg: DDPGConfig, spec: TensorSpec) -> DDPGLoss:
        return DDPGLoss(
            self.actor,
            self.critic,
            loss_function=cfg.loss_function,
            delay_actor=True,
            delay_value=True,
        )

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        return (
            list(self.loss.actor_network_params.flatten_keys().values()),
            list(self.loss.value_network_params.flatten_keys().values()),
        )

    def make_fast_path(self) -> None:
        target_critic = self.loss.target_value_network_params.get("module")
        self.__dict__["_target_critic"] = with_params(self.critic_module, target_critic, live=True)
        self._fast_losses = self.compiled(self._plain_losses)

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
        loss_value = distance(pred, target, self.cfg.loss_function).mean()
        u = self.actor_module(*obs)
        detached = {n: p.detach() for n, p in self.critic_module.named_parameters()}
        q = functional_call(self.critic_module, detached, (*obs, self.squash(u)))
        return -q.mean(), loss_value, self.penalty(u)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        if self.cfg.fast_update:
            loss_actor, loss_value, penalty = self._fast_losses(batch)
            out = {"loss_actor": loss_actor, "loss_value": loss_value}
        else:
            out, penalty = self.with_saturation_penalty(self.loss, batch)
        self._check_losses(loss_actor=out["loss_actor"], loss_value=out["loss_value"])
        # Sum only the loss terms: other entries (pred_value, ...) are not detached.
        self._step(out["loss_actor"] + out["loss_value"] + penalty)
        self.target_updater.step()
        self.num_updates += 1
        return {
            "loss_actor": out["loss_actor"].detach(),
            "loss_value": out["loss_value"].detach(),
            "grad_norm_actor": self.grad_norms["actor"],
            "grad_norm_critic": self.grad_norms["critic"],
        }

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``Q_target(s, mu_target(s))``."""
        loss = self.loss
        return ActorCriticValue(
            with_params(self.actor, loss.target_actor_network_params, live=live),
            [with_params(self.critic, loss.target_value_network_params, live=live)],
        )
