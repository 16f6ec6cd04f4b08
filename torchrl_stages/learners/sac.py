"""SAC for continuous-action stages, and its soft stage value."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.modules.distributions.utils import rsample_and_log_prob
from torchrl.objectives import SACLoss
from torchrl.objectives.utils import distance_loss

from torchrl_stages.config.bounds import free, positive
from torchrl_stages.learners.actor_critic import (
    ActorCriticConfig,
    ActorCriticLearner,
    EntropyRegularized,
)
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.networks import Chain
from torchrl_stages.learners.ops import stacked_calls, td0_target
from torchrl_stages.learners.stacking import per_seed, seed_rows


@dataclass
class SACConfig(ActorCriticConfig):
    """SAC stage (continuous, bounded actions): a tanh-Gaussian policy, twin critics and an
    entropy coefficient tuned to a target entropy (``SACLoss``'s objective, version 2)."""

    algo: str = free("sac")
    # the entropy coefficient at the start; small, so that the entropy bonus over an episode,
    # about alpha |H| / (1 - gamma), stays well under the rewards (torchrl's default: 1)
    alpha_init: float = positive(0.01)
    alpha_lr: float = positive(3e-4)  # its learning rate (automatic entropy tuning)
    # any number; null: -(action dimensions), torchrl's "auto"
    target_entropy: float | None = free(None)
    # actions per state in the stage value's expectation E_a[min_i Q_i(s, a) - alpha log pi]
    value_samples: int = positive(16)


class SoftValue(nn.Module):
    """``V(s) = E_{a ~ pi(s)}[min_i Q_i(s, a) - alpha log pi(a|s)]``, SAC's soft value, as the
    mean over ``samples`` actions of fixed noise (``V`` is a function of ``s``; every seed gets
    that noise); ``actor`` maps observations to ``(loc, scale)``."""

    def __init__(self, actor, critic, critic_params, log_alpha, dist_kwargs, samples) -> None:
        super().__init__()
        self.actor, self.critic, self.critic_params = actor, critic, critic_params
        self.log_alpha, self.dist_kwargs, self.samples = log_alpha, dict(dist_kwargs), int(samples)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        loc, scale = self.actor(*obs)
        lead, dim = loc.shape[:-1], loc.shape[-1]
        alpha = seed_rows(self.log_alpha).detach().exp()
        n = alpha.shape[0] if alpha.ndim else 1
        # [seeds, 1, M, d]: the samples' axis behind the seeds (stacked layers read seed-major)
        loc, scale = (t.reshape(n, 1, -1, dim) for t in (loc, scale))
        dist = TanhNormal(loc, scale, **self.dist_kwargs)
        devices = [loc.device] if loc.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed(0)
            noise = torch.empty(self.samples, *loc.shape[-2:], device=loc.device).normal_()
        # what TanhNormal.rsample_and_log_prob computes, on the noise every seed shares
        preimage = loc + noise * scale
        squash = dist.transforms[0]
        action = squash(preimage)
        jacobian = squash.log_abs_det_jacobian(preimage, action).sum(-1)
        log_prob = dist.base_dist.log_prob(preimage) - jacobian
        obs_k = [o.reshape(n, 1, -1, *o.shape[len(lead) :]) for o in obs]
        obs_k = [o.expand(n, self.samples, *o.shape[2:]) for o in obs_k]
        q = torch.stack(stacked_calls(self.critic, self.critic_params, *obs_k, action)).amin(0)
        soft = q - per_seed(alpha, q) * log_prob.unsqueeze(-1)
        return soft.mean(1).reshape(*lead, 1)


@register_algorithm
class SACLearner(EntropyRegularized, ActorCriticLearner):
    """SAC for one stage: a tanh-Gaussian actor (its mean the greedy policy), twin critics and
    a tuned entropy coefficient in torchrl's ``SACLoss`` (version 2), the update on plain tensors.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> specs = StageSpecs(["observation"], 3, "action", Bounded(-1.0, 1.0, shape=(2,)))
        >>> learner = SACLearner(SACConfig(), specs)
        >>> sorted(learner.optimizers), learner.value().out_keys
        (['actor', 'alpha', 'critic'], ['state_value'])
    """

    algo = "sac"
    Config = SACConfig
    torchrl_loss = SACLoss
    update_draws_random = True  # its actions are sampled
    stacks_seeds = True
    ACTOR_PATH = ("module", "0", "module", "0")
    ACTOR_OUTPUTS = 2  # the location and (pre-softplus) scale

    def __init__(self, cfg: SACConfig, specs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        self.loss.target_entropy  # noqa: B018 - a lazy buffer: in the state dict from the start
        self.learn_alpha()

    def make_actor(self, actor_net: nn.Module, spec: TensorSpec) -> TensorDictModuleBase:
        net = Chain(actor_net, NormalParamExtractor())
        loc_scale = TensorDictModule(net, self.specs.observation_keys, ["loc", "scale"])
        return ProbabilisticActor(
            loc_scale,
            in_keys=["loc", "scale"],
            out_keys=[self.specs.action_key],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        )

    def loss_kwargs(self, cfg: SACConfig) -> dict:
        return {
            **super().loss_kwargs(cfg),
            "alpha_init": cfg.alpha_init,
            "target_entropy": "auto" if cfg.target_entropy is None else cfg.target_entropy,
            # a shared encoder needs a target copy (the target actor's) for the target critics
            "delay_actor": self.shared_encoder,
        }

    def _dist(self, out: torch.Tensor) -> TanhNormal:
        """The policy's distribution from the actor network's output."""
        loc, scale = self.actor[0].module[1](out)  # its NormalParamExtractor
        return TanhNormal(loc, scale, **self.actor[1].distribution_kwargs)

    def _plain_losses(self, batch: TensorDictBase):
        """``SACLoss`` (version 2), its two draws in its order (the next actions, then the
        actor's); a shared encoder is trained by the critics' loss alone."""
        critics = self.loss.qvalue_network_params
        with torch.no_grad():
            next_obs = self.inputs(batch, nxt=True)
            next_out = self.actor_head(self.features(next_obs))
            next_action, next_log_prob = rsample_and_log_prob(self._dist(next_out))
            next_features = self.features(next_obs, target=True)
            targets = self.loss.target_qvalue_network_params
            next_q = self.critic_values(targets, next_features, next_action)
            next_log_prob = next_log_prob.unsqueeze(-1)
            soft = torch.stack(next_q) - self.alpha(next_log_prob) * next_log_prob
            target = td0_target(batch, soft.min(0).values, self.cfg.gamma)
        features = self.features(self.inputs(batch))
        preds = torch.stack(self.critic_values(critics, features, batch.get(self.specs.action_key)))
        distances = distance_loss(preds, target.expand_as(preds), self.cfg.loss_function)
        loss_q = self.batch_mean(distances.sum(0))
        features = [f.detach() for f in features]
        action, log_prob = rsample_and_log_prob(self._dist(self.actor_head(features)))
        q = torch.stack(self.critic_values(critics, features, action, detach=True))
        loss_actor = self.batch_mean(self.alpha(log_prob) * log_prob - q.min(0).values.squeeze(-1))
        return loss_actor, loss_q, self.alpha_loss(log_prob)

    @classmethod
    def value_from_loss(
        cls, loss: SACLoss, live: bool = False, critics=None, samples: int = 16
    ) -> TensorDictModuleBase:
        """:class:`SoftValue` of a ``SACLoss``'s target critics (or ``critics``)."""
        if critics is None:
            critics = loss.target_qvalue_network_params
        kwargs = loss.actor_network[1].distribution_kwargs
        return cls.soft_value(SoftValue, loss, critics["module"], live, kwargs, samples)

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """:class:`SoftValue`; with a shared encoder the critics read the target one."""
        return self.value_from_loss(self.loss, live, self.target_critics(), self.cfg.value_samples)
