"""Discrete SAC for discrete-action stages: its config, learner, checks and soft stage value."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import OneHot
from torchrl.modules import OneHotCategorical, ProbabilisticActor, ValueOperator
from torchrl.objectives import DiscreteSACLoss, ValueEstimators

from torchrl_stages.config import StageChecks, StageConfig
from torchrl_stages.config.bounds import free, in_range, one_of, positive
from torchrl_stages.learners.base import (
    LOSS_FUNCTIONS,
    Learner,
    StageSpecs,
    check_loss_function,
    register_algorithm,
)
from torchrl_stages.learners.entropy import EntropyRegularized
from torchrl_stages.learners.networks import mlp
from torchrl_stages.learners.ops import FusedSoftUpdate, distance, stacked_calls, td0_target
from torchrl_stages.learners.stacking import per_seed, seed_rows
from torchrl_stages.values import with_params


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
    # the target entropy is this fraction of the uniform policy's, log(number of actions).
    # Low: an episode that does not end collects the entropy bonus at every step, so a high
    # target (torchrl's default 0.98) made wandering worth more than the goal (0% success in
    # the grid world, values growing past 1.8); at 0.1 alpha decays and the greedy path is
    # optimal
    target_entropy_weight: float = in_range(0, 1, 0.1)


def _log_probs(probs: torch.Tensor) -> torch.Tensor:
    """``log pi`` as ``DiscreteSACLoss`` takes it for its target (a zero probability as 1e-8)."""
    return torch.log(torch.where(probs == 0, 1e-8, probs))


class DiscreteSoftValue(nn.Module):
    """``V(s) = sum_a pi(a|s) (min_i Q_i(s, a) - alpha log pi(a|s))``: the exact soft value
    of discrete SAC's critic targets.

    Args:
        actor: the actor network (observations in, logits out).
        critic: the critic network (observations in, every action's value out).
        critic_params: the stacked parameters of the twin critics (``[num_critics, ...]``).
        log_alpha: the entropy coefficient's log (a tensor it reads at every call; one per
            seed, ``[N]``, for seed-stacked networks, whose observations are seed-major).
    """

    def __init__(self, actor: nn.Module, critic: nn.Module, critic_params, log_alpha) -> None:
        super().__init__()
        self.actor, self.critic = actor, critic
        self.critic_params, self.log_alpha = critic_params, log_alpha

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        probs = torch.distributions.Categorical(logits=self.actor(*obs)).probs
        q = torch.stack(stacked_calls(self.critic, self.critic_params, *obs)).amin(0)
        alpha = per_seed(seed_rows(self.log_alpha).detach().exp(), probs)
        soft = q - alpha * _log_probs(probs)
        return (probs * soft).sum(-1, keepdim=True)


@register_algorithm
class DiscreteSACLearner(EntropyRegularized, Learner):
    """Discrete SAC for one stage: a categorical actor sampled for exploration (its most likely
    action is the greedy policy), twin critics of every action's value, and the entropy
    coefficient tuned so that the policy's entropy tracks ``target_entropy_weight`` of the
    uniform one's. Its parameters live in torchrl's ``DiscreteSACLoss``; its update runs
    :meth:`_plain_losses`, what that module computes on plain tensors
    (``tests/test_losses.py`` pins the two equal). The stage value is the exact soft value
    :class:`DiscreteSoftValue`.

    Examples:
        >>> from torchrl.data import Categorical
        >>> from torchrl_stages.learners import StageSpecs
        >>> from torchrl_stages.learners.discrete_sac import DiscreteSACConfig, DiscreteSACLearner
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
        spec = specs.action_spec
        num_actions = spec.space.n
        inputs, cells, fourier = specs.input_shapes, list(cfg.num_cells), cfg.fourier_features
        actor_net = mlp(inputs, num_actions, cells, fourier, self.cnn)
        self.actor = ProbabilisticActor(
            TensorDictModule(actor_net, in_keys=specs.observation_keys, out_keys=["logits"]),
            in_keys=["logits"],
            out_keys=[specs.action_key],
            spec=spec,
            distribution_class=(
                OneHotCategorical if isinstance(spec, OneHot) else torch.distributions.Categorical
            ),
        )
        self.critic = ValueOperator(
            mlp(inputs, num_actions, cells, fourier, self.cnn),
            in_keys=specs.observation_keys,
            out_keys=["action_value"],
        )
        self.policy = self.exploration_policy = self.actor
        self.loss = DiscreteSACLoss(
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
        self.loss.set_keys(action=specs.action_key)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = FusedSoftUpdate(self.loss, tau=cfg.tau)
        self.stack_alpha()
        self.optimizers = {
            "actor": self.adam(self.loss.actor_network_params.values(True, True), cfg.actor_lr),
            "critic": self.adam(self.loss.qvalue_network_params.values(True, True), cfg.lr),
            "alpha": self.adam([self.loss.log_alpha], cfg.alpha_lr),
        }
        self._losses = self.compiled(self._plain_losses)

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        check_loss_function(checks)
        checks.positive("actor_lr", 1e-3)
        cls.validate_entropy(checks)
        checks.fraction("target_entropy_weight")

    @property
    def actor_module(self) -> nn.Module:
        """The actor network: observation tensors in, one logit per action out."""
        return self.actor[0].module

    @property
    def critic_module(self) -> nn.Module:
        """The critic network: observation tensors in, one value per action out."""
        return self.critic.module

    def _chosen(self, q: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Each critic's value of the action taken (``[num_critics, B, 1]``)."""
        if isinstance(self.specs.action_spec, OneHot):
            return (q * action.to(q.dtype)).sum(-1, keepdim=True)
        index = action.reshape(1, *q.shape[1:-1], 1).expand(*q.shape[:-1], 1)
        return q.gather(-1, index)

    def _plain_losses(self, batch: TensorDictBase):
        """What ``DiscreteSACLoss`` computes, on plain tensors: every critic against
        ``r + gamma (1 - terminated) V_target(s')`` (summed over the twins), the actor's
        ``sum_a pi (alpha log pi - min_i Q_i)`` and the entropy coefficient's loss."""
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        critics, targets = self.loss.qvalue_network_params, self.loss.target_qvalue_network_params
        with torch.no_grad():
            next_probs = torch.distributions.Categorical(logits=self.actor_module(*next_obs)).probs
            next_q = torch.stack(stacked_calls(self.critic_module, targets["module"], *next_obs))
            soft = next_q.min(0).values - self.alpha(next_probs) * _log_probs(next_probs)
            target = td0_target(
                batch.get("next"),
                (next_probs * soft).sum(-1, keepdim=True),
                float(self.cfg.gamma),
                batch.get("steps_to_next_obs", None),
            )
        q = torch.stack(stacked_calls(self.critic_module, critics["module"], *obs))
        chosen = self._chosen(q, batch.get(self.specs.action_key))
        distances = distance(chosen, target.expand_as(chosen), self.cfg.loss_function)
        loss_q = self.batch_mean(distances.sum(0))
        dist = torch.distributions.Categorical(logits=self.actor_module(*obs))
        probs, log_probs = dist.probs, dist.logits
        detached = critics["module"].detach()
        min_q = torch.stack(stacked_calls(self.critic_module, detached, *obs)).min(0).values
        loss_actor = self.batch_mean((probs * (self.alpha(probs) * log_probs - min_q)).sum(-1))
        return loss_actor, loss_q, self.alpha_loss((log_probs * probs).sum(-1))

    @classmethod
    def value_from_loss(cls, loss: DiscreteSACLoss, live: bool = False) -> TensorDictModuleBase:
        """The exact soft value (:class:`DiscreteSoftValue`) of a ``DiscreteSACLoss`` with
        target critics, its actor a ``ProbabilisticActor`` over a ``TensorDictModule``
        writing logits."""
        network = loss.actor_network[0]
        actor = with_params(
            network.module, loss.actor_network_params["module", "0", "module"], live=live
        )
        critics = loss.target_qvalue_network_params["module"]
        module = DiscreteSoftValue(
            actor,
            loss.qvalue_network.module,
            critics if live else critics.detach().clone(),
            loss.log_alpha if live else loss.log_alpha.detach().clone(),
        )
        return TensorDictModule(module, in_keys=list(network.in_keys), out_keys=["state_value"])

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``sum_a pi(a|s) (min_i Q_i,target(s, a) - alpha log pi(a|s))``, the actor and
        ``alpha`` as they are."""
        return self.value_from_loss(self.loss, live=live)
