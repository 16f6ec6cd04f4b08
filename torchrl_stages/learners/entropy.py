"""What the maximum-entropy learners (SAC, discrete SAC) share: a learned entropy coefficient."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from torchrl_stages.config import StageChecks
from torchrl_stages.learners.stacking import per_seed, seed_rows
from torchrl_stages.values import with_params


class EntropyRegularized:
    """A :class:`~torchrl_stages.learners.Learner` mixin: ``loss.log_alpha`` (one per seed) and
    ``_losses(batch)``, the actor's, critics' and alpha's losses, stepped together."""

    lr_keys = ("lr", "actor_lr", "alpha_lr")

    def stack_alpha(self) -> None:
        """Gives a seed-stacked learner one ``log_alpha`` per seed (``[N]``)."""
        if self.seeds is not None:
            log_alpha = self.loss.log_alpha.detach()
            self.loss.log_alpha = nn.Parameter(log_alpha.expand(self.seeds).clone())

    def alpha(self, like: torch.Tensor) -> torch.Tensor:
        """The entropy coefficient, detached, shaped to broadcast against ``like``."""
        return per_seed(seed_rows(self.loss.log_alpha).detach().exp(), like)

    def alpha_loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``-log_alpha (log pi + target_entropy)`` over the batch."""
        entropy_gap = log_prob.detach() + self.loss.target_entropy
        log_alpha = per_seed(seed_rows(self.loss.log_alpha), entropy_gap)
        return self.batch_mean(-log_alpha * entropy_gap)

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        super().validate(checks)
        checks.positive("alpha_init", 0.01)
        checks.positive("alpha_lr", 3e-4)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_actor, loss_q, loss_alpha = self._losses(batch)
        losses = {"loss_actor": loss_actor, "loss_qvalue": loss_q, "loss_alpha": loss_alpha}
        out = self._apply(losses, loss_actor + loss_q + loss_alpha)
        self.num_updates += 1
        return {
            **out,
            "alpha": seed_rows(self.loss.log_alpha).detach().exp().clone(),
            "grad_norm_actor": self.grad_norms["actor"],
            "grad_norm_critic": self.grad_norms["critic"],
        }

    def anneal_exploration(self, frames: int) -> None:
        """Nothing to anneal: the entropy coefficient is learned."""


def soft_value(module: type[nn.Module], loss, actor, critic, critics, live: bool, *args):
    """``module`` (a soft value) of ``loss``'s actor, the ``critics`` parameters of ``critic``
    and ``log_alpha`` (read in place with ``live``, else copies) as a ``TensorDictModule``."""
    network = actor[0]
    params = loss.actor_network_params["module", "0", "module"]
    value = module(
        with_params(network.module, params, live=live),
        critic,
        critics if live else critics.detach().clone(),
        loss.log_alpha if live else loss.log_alpha.detach().clone(),
        *args,
    )
    return TensorDictModule(value, in_keys=list(network.in_keys), out_keys=["state_value"])
