"""What the maximum-entropy learners share: one step on their three losses and a learned
entropy coefficient ``alpha`` instead of an exploration schedule."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from torchrl_stages.config import StageChecks
from torchrl_stages.learners.ops import detached_copy
from torchrl_stages.learners.stacking import per_seed, seed_rows


class EntropyRegularized:
    """A mixin for :class:`~torchrl_stages.learners.Learner` subclasses whose ``loss`` module
    has a ``log_alpha`` parameter and whose ``_losses(batch)`` returns the actor's, the
    critics' and the entropy coefficient's losses, all stepped together (their gradients do
    not overlap: the actor's loss reads the critics detached, the coefficient's the
    log-probabilities). Stacked for seeds, ``log_alpha`` holds one coefficient per seed
    (``[N]``, :meth:`stack_alpha`)."""

    lr_keys = ("lr", "actor_lr", "alpha_lr")

    def stack_alpha(self) -> None:
        """Gives a seed-stacked learner one entropy coefficient per seed (``log_alpha``:
        ``[N]``, each the config's ``alpha_init``); an ordinary learner keeps its scalar."""
        if self.seeds is not None:
            log_alpha = self.loss.log_alpha.detach()
            self.loss.log_alpha = nn.Parameter(log_alpha.expand(self.seeds).clone())

    def alpha(self, like: torch.Tensor) -> torch.Tensor:
        """The entropy coefficient, detached, shaped to broadcast against ``like`` (a batch's
        per-sample term, seed-major when stacked: each seed's own coefficient)."""
        return per_seed(seed_rows(self.loss.log_alpha).detach().exp(), like)

    def alpha_loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``-log_alpha (log pi + target_entropy)`` over the batch (one per seed when
        stacked), ``log_prob`` the policy's log-probabilities (their expectation for a
        discrete policy)."""
        entropy_gap = log_prob.detach() + self.loss.target_entropy
        log_alpha = per_seed(seed_rows(self.loss.log_alpha), entropy_gap)
        return self.batch_mean(-log_alpha * entropy_gap)

    @staticmethod
    def validate_entropy(checks: StageChecks) -> None:
        checks.positive("alpha_init", 0.01)
        checks.positive("alpha_lr", 3e-4)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_actor, loss_q, loss_alpha = self._losses(batch)
        self._check_losses(loss_actor=loss_actor, loss_qvalue=loss_q, loss_alpha=loss_alpha)
        self._step(loss_actor + loss_q + loss_alpha)
        self.target_updater.step()
        self.num_updates += 1
        return {
            "loss_actor": detached_copy(loss_actor),
            "loss_qvalue": detached_copy(loss_q),
            "loss_alpha": detached_copy(loss_alpha),
            "alpha": seed_rows(self.loss.log_alpha).detach().exp().clone(),
            "grad_norm_actor": self.grad_norms["actor"],
            "grad_norm_critic": self.grad_norms["critic"],
        }

    def anneal_exploration(self, frames: int) -> None:
        """Nothing to anneal: the entropy coefficient is learned."""
