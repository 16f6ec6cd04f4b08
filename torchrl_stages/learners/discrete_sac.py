"""Discrete SAC for discrete-action stages, and its exact soft stage value."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import OneHot
from torchrl.modules import OneHotCategorical, ProbabilisticActor, ValueOperator
from torchrl.objectives import DiscreteSACLoss
from torchrl.objectives.utils import distance_loss

from torchrl_stages.config import StageConfig
from torchrl_stages.config.bounds import free, in_range, one_of, positive
from torchrl_stages.learners.actor_critic import EntropyRegularized
from torchrl_stages.learners.base import LOSS_FUNCTIONS, Learner, StageSpecs, register_algorithm
from torchrl_stages.learners.ops import stacked_calls, taken, td0_target
from torchrl_stages.learners.stacking import per_seed, seed_rows


@dataclass
class DiscreteSACConfig(StageConfig):
    """Discrete SAC stage: a categorical policy, twin critics of every action's value and an
    entropy coefficient tuned to a target entropy (``DiscreteSACLoss``'s objective)."""

    algo: str = free("discrete_sac")
    actor_lr: float = positive(1e-3)
    loss_function: str = one_of(*LOSS_FUNCTIONS, default="l2")
    # the entropy coefficient at the start, small for the reason SACConfig.alpha_init gives
    alpha_init: float = positive(0.01)
    alpha_lr: float = positive(3e-4)  # its learning rate (automatic entropy tuning)
    # the target entropy as a fraction of the uniform policy's, log(number of actions); low,
    # or the entropy bonus makes wandering worth more than the goal (torchrl's default: 0.98)
    target_entropy_weight: float = in_range(0, 1, 0.1)


class DiscreteSoftValue(nn.Module):
    """``V(s) = sum_a pi(a|s) (min_i Q_i(s, a) - alpha log pi(a|s))`` of the ``critic_params``
    and ``log_alpha`` it holds (``actor``: observations to logits, ``critic``: to Q(s, .))."""

    def __init__(self, actor: nn.Module, critic: nn.Module, critic_params, log_alpha) -> None:
        super().__init__()
        self.actor, self.critic = actor, critic
        self.critic_params, self.log_alpha = critic_params, log_alpha

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        return self.of(self.actor, self.critic, self.critic_params, self.log_alpha, obs)

    @staticmethod
    def of(actor, critic, critic_params, log_alpha, obs) -> torch.Tensor:
        probs = torch.distributions.Categorical(logits=actor(*obs)).probs
        q = torch.stack(stacked_calls(critic, critic_params, *obs)).amin(0)
        alpha = per_seed(seed_rows(log_alpha).detach().exp(), probs)
        # a zero probability's log is that of 1e-8, as in DiscreteSACLoss's target
        soft = q - alpha * torch.log(torch.where(probs == 0, 1e-8, probs))
        return (probs * soft).sum(-1, keepdim=True)


@register_algorithm
class DiscreteSACLearner(EntropyRegularized, Learner):
    """Discrete SAC for one stage: a categorical actor, twin critics of every action's value
    and a tuned entropy coefficient in torchrl's ``DiscreteSACLoss``, the update on plain tensors.

    Examples:
        >>> from torchrl.data import Categorical
        >>> specs = StageSpecs(["observation"], 2, "action", Categorical(4))
        >>> learner = DiscreteSACLearner(DiscreteSACConfig(), specs)
        >>> sorted(learner.optimizers), learner.value().out_keys
        (['actor', 'alpha', 'critic'], ['state_value'])
    """

    algo = "discrete_sac"
    Config = DiscreteSACConfig
    action_spaces = ("discrete",)
    torchrl_loss = DiscreteSACLoss
    stacks_seeds = True

    def __init__(self, cfg: DiscreteSACConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        spec, obs = specs.action_spec, specs.observation_keys
        num_actions = spec.space.n
        logits = TensorDictModule(self.network(num_actions), obs, ["logits"])
        dist = OneHotCategorical if isinstance(spec, OneHot) else torch.distributions.Categorical
        self.actor = ProbabilisticActor(
            logits, ["logits"], [specs.action_key], spec=spec, distribution_class=dist
        )
        self.critic = ValueOperator(self.network(num_actions), obs, ["action_value"])
        self.policy = self.exploration_policy = self.actor
        loss = DiscreteSACLoss(
            self.actor,
            self.critic,
            action_space=spec,
            num_actions=num_actions,
            num_qvalue_nets=2,
            loss_function=cfg.loss_function,
            alpha_init=cfg.alpha_init,
            target_entropy_weight=cfg.target_entropy_weight,
            delay_qvalue=True,
        )
        self.use_loss(loss)
        self.optimizers = {
            "actor": self.adam(self.loss.actor_network_params.values(True, True), cfg.actor_lr),
            "critic": self.adam(self.loss.qvalue_network_params.values(True, True), cfg.lr),
        }
        self.learn_alpha()
        self._losses = self.compiled(self._plain_losses)

    def _plain_losses(self, batch: TensorDictBase):
        """``DiscreteSACLoss``: the actor's, the critics' and the entropy coefficient's losses."""
        actor, critic = self.actor[0].module, self.critic.module
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        critics = self.loss.qvalue_network_params
        with torch.no_grad():
            targets = self.loss.target_qvalue_network_params["module"]
            next_value = DiscreteSoftValue.of(actor, critic, targets, self.loss.log_alpha, next_obs)
            target = td0_target(batch, next_value, self.cfg.gamma)
        q = torch.stack(stacked_calls(critic, critics["module"], *obs))
        one_hot = isinstance(self.specs.action_spec, OneHot)
        chosen = taken(q, batch.get(self.specs.action_key), one_hot, lead=1)
        distances = distance_loss(chosen, target.expand_as(chosen), self.cfg.loss_function)
        loss_q = self.batch_mean(distances.sum(0))
        dist = torch.distributions.Categorical(logits=actor(*obs))
        probs, log_probs = dist.probs, dist.logits
        frozen = stacked_calls(critic, critics["module"], *obs, detach=True)  # the actor's
        min_q = torch.stack(frozen).min(0).values
        loss_actor = self.batch_mean((probs * (self.alpha(probs) * log_probs - min_q)).sum(-1))
        return loss_actor, loss_q, self.alpha_loss((log_probs * probs).sum(-1))

    @classmethod
    def value_from_loss(cls, loss: DiscreteSACLoss, live: bool = False) -> TensorDictModuleBase:
        """:class:`DiscreteSoftValue` of a ``DiscreteSACLoss``'s target critics."""
        critics = loss.target_qvalue_network_params["module"]
        return cls.soft_value(DiscreteSoftValue, loss, critics, live)

    def value(self, live: bool = False) -> TensorDictModuleBase:
        return self.value_from_loss(self.loss, live=live)
