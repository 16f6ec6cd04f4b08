"""DDPG stage learner (continuous, bounded actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import TensorSpec
from torchrl.objectives import DDPGLoss

from torchrl_stages.config import DDPGConfig
from torchrl_stages.learners.actor_critic import ActorCriticLearner
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

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
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
