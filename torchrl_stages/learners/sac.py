"""SAC for continuous-action stages: its config, learner, checks and soft stage value."""

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

from torchrl_stages.config import StageChecks
from torchrl_stages.config.bounds import free, positive
from torchrl_stages.learners.actor_critic import ActorCriticConfig, ActorCriticLearner
from torchrl_stages.learners.base import register_algorithm
from torchrl_stages.learners.entropy import EntropyRegularized
from torchrl_stages.learners.networks import Chain
from torchrl_stages.learners.ops import distance, stacked_calls, td0_target
from torchrl_stages.learners.stacking import per_seed, seed_rows
from torchrl_stages.values import with_params


@dataclass
class SACConfig(ActorCriticConfig):
    """SAC stage (continuous, bounded actions): a tanh-Gaussian policy, twin critics and an
    entropy coefficient tuned to a target entropy (``SACLoss``'s objective, version 2)."""

    algo: str = free("sac")
    # the entropy coefficient at the start. Small: the entropy bonus summed over an episode,
    # about alpha |H| / (1 - gamma), must stay well under the tasks' unit rewards, or the soft
    # value a stage hands on is mostly entropy (alpha 1, torchrl's default, left the
    # manipulator's stages at 0% success with values 12 off; 0.01 reached 100%)
    alpha_init: float = positive(0.01)
    alpha_lr: float = positive(3e-4)  # its learning rate (automatic entropy tuning)
    # any number; null: -(action dimensions), torchrl's "auto"
    target_entropy: float | None = free(None)
    # actions per state in the stage value's expectation E_a[min_i Q_i(s, a) - alpha log pi]
    value_samples: int = positive(16)


class SoftValue(nn.Module):
    """``V(s) = E_{a ~ pi(s)}[min_i Q_i(s, a) - alpha log pi(a|s)]``, the soft value SAC's
    critic targets use, as the mean over ``samples`` actions drawn with fixed noise (a seeded
    generator of its own: ``V`` is a function of ``s``, and the global one is left alone).

    Seed-stacked (``log_alpha`` one per seed, ``[N]``), its observations are seed-major and
    each seed's block of states gets the same noise, that of an ordinary learner's ``V`` on
    that block alone.

    Args:
        actor: the actor network and its ``NormalParamExtractor`` (observations in,
            ``(loc, scale)`` out).
        critic: the critic network (observations and action in, ``Q`` out).
        critic_params: the stacked parameters of the twin critics (``[num_critics, ...]``).
        log_alpha: the entropy coefficient's log (a tensor it reads at every call).
        dist_kwargs: the ``TanhNormal``'s bounds.
    """

    def __init__(self, actor, critic, critic_params, log_alpha, dist_kwargs, samples) -> None:
        super().__init__()
        self.actor, self.critic, self.samples = actor, critic, int(samples)
        self.critic_params = critic_params
        self.log_alpha, self.dist_kwargs = log_alpha, dict(dist_kwargs)

    def forward(self, *obs: torch.Tensor) -> torch.Tensor:
        loc, scale = self.actor(*obs)
        lead, dim = loc.shape[:-1], loc.shape[-1]
        alpha = seed_rows(self.log_alpha).detach().exp()
        n = alpha.shape[0] if alpha.ndim else 1
        # [seeds, 1, M, d]: each seed's block of M states, the samples' axis behind the seeds
        # (stacked layers read seed-major inputs)
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
    """SAC for one stage: a tanh-Gaussian actor sampled for exploration (its mean is the greedy
    policy), twin critics, and the entropy coefficient ``alpha`` tuned so that the policy's
    entropy tracks ``target_entropy``. Its parameters live in torchrl's ``SACLoss`` (built as
    torchrl builds them); its update runs :meth:`_plain_losses`, what that module computes on
    plain tensors (``tests/test_losses.py`` pins the two equal, gradients included). The stage
    value is the soft value :class:`SoftValue`.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl_stages.learners import StageSpecs
        >>> from torchrl_stages.learners.sac import SACConfig, SACLearner
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

    def __init__(self, cfg: SACConfig, specs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        self.loss.target_entropy  # noqa: B018 - a lazy buffer: in the state dict from the start
        self.stack_alpha()
        self.optimizers["alpha"] = self.adam([self.loss.log_alpha], cfg.alpha_lr)

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        super().validate(checks)
        cls.validate_entropy(checks)
        checks.positive("value_samples", 16)

    def actor_outputs(self, action_dim: int) -> int:
        return 2 * action_dim  # the location and (pre-softplus) scale of each dimension

    def make_actor(self, actor_net: nn.Module, spec: TensorSpec) -> TensorDictModuleBase:
        keys = self.specs
        return ProbabilisticActor(
            TensorDictModule(
                Chain(actor_net, NormalParamExtractor()),
                in_keys=keys.observation_keys,
                out_keys=["loc", "scale"],
            ),
            in_keys=["loc", "scale"],
            out_keys=[keys.action_key],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        )

    def make_loss(self, cfg: SACConfig, spec: TensorSpec) -> SACLoss:
        # a shared encoder needs a target copy of it (the target actor's, as in TD3): the
        # target critics read s' through it
        loss = SACLoss(
            self.actor,
            self.critic,
            num_qvalue_nets=2,
            loss_function=cfg.loss_function,
            alpha_init=cfg.alpha_init,
            action_spec=spec,
            target_entropy="auto" if cfg.target_entropy is None else cfg.target_entropy,
            delay_actor=self.shared_encoder,
            delay_qvalue=True,
            separate_losses=self.shared_encoder,
        )
        return self.with_action_key(loss)

    def make_losses(self) -> None:
        losses = self._shared_losses if self.shared_encoder else self._plain_losses
        self._losses = self.compiled(losses)

    def _dist(self, out: torch.Tensor) -> TanhNormal:
        """The policy's distribution from the actor network's output."""
        loc, scale = self.actor[0].module[1](out)  # its NormalParamExtractor
        return TanhNormal(loc, scale, **self.actor[1].distribution_kwargs)

    def _soft_target(
        self, batch: TensorDictBase, next_q: list[torch.Tensor], next_log_prob: torch.Tensor
    ) -> torch.Tensor:
        """``r + gamma (1 - terminated) min_i (Q_i,target(s', a') - alpha log pi(a'|s'))``."""
        next_log_prob = next_log_prob.unsqueeze(-1)
        soft = torch.stack(next_q) - self.alpha(next_log_prob) * next_log_prob
        return td0_target(
            batch.get("next"),
            soft.min(0).values,
            float(self.cfg.gamma),
            batch.get("steps_to_next_obs", None),
        )

    def _critic_and_alpha_losses(self, preds, target, q_actor, log_prob):
        """The critics' loss (summed over the twins), the actor's ``alpha log pi - min_i Q_i``
        and the entropy coefficient's ``-log_alpha (log pi + target_entropy)``."""
        preds = torch.stack(preds)
        distances = distance(preds, target.expand_as(preds), self.cfg.loss_function)
        loss_q = self.batch_mean(distances.sum(0))
        q = torch.stack(q_actor).min(0).values.squeeze(-1)
        loss_actor = self.batch_mean(self.alpha(log_prob) * log_prob - q)
        return loss_actor, loss_q, self.alpha_loss(log_prob)

    def _plain_losses(self, batch: TensorDictBase):
        """What ``SACLoss`` computes (version 2, no value network), on plain tensors, its two
        draws in its order: the next actions for the critics' target, then the actor's."""
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        critics, targets = self.loss.qvalue_network_params, self.loss.target_qvalue_network_params
        with torch.no_grad():
            next_action, next_log_prob = rsample_and_log_prob(
                self._dist(self.actor_module(*next_obs))
            )
            next_q = self.critic_values(targets["module"], *next_obs, next_action)
            target = self._soft_target(batch, next_q, next_log_prob)
        preds = self.critic_values(critics["module"], *obs, batch.get(self.specs.action_key))
        action, log_prob = rsample_and_log_prob(self._dist(self.actor_module(*obs)))
        q_actor = self.critic_values(critics["module"].detach(), *obs, action)
        return self._critic_and_alpha_losses(preds, target, q_actor, log_prob)

    def _shared_losses(self, batch: TensorDictBase):
        """:meth:`_plain_losses` with one encoder: ``s`` is encoded once by the trained encoder
        (trained by the critics' loss; the actor reads its features detached), ``s'`` by the
        trained one for the actor and by the target one for the target critics."""
        obs, next_obs = self.inputs(batch), self.inputs(batch, nxt=True)
        encoder, actor_head = self.actor_module.encoder, self.actor_module.body
        heads = self.loss.qvalue_network_params["module", "body"]
        with torch.no_grad():
            next_action, next_log_prob = rsample_and_log_prob(
                self._dist(actor_head(encoder(*next_obs)))
            )
            target_features = self._target_actor.encoder(*next_obs)
            target_heads = self.loss.target_qvalue_network_params["module", "body"]
            next_q = self.head_values(target_heads, target_features, next_action)
            target = self._soft_target(batch, next_q, next_log_prob)
        features = encoder(*obs)
        preds = self.head_values(heads, features, batch.get(self.specs.action_key))
        features = features.detach()
        action, log_prob = rsample_and_log_prob(self._dist(actor_head(features)))
        q_actor = self.head_values(heads.detach(), features, action)
        return self._critic_and_alpha_losses(preds, target, q_actor, log_prob)

    @classmethod
    def value_from_loss(cls, loss: SACLoss, live: bool = False) -> TensorDictModuleBase:
        """The soft value (:class:`SoftValue`, 16 actions per state) of a ``SACLoss``
        (version 2) with target critics, its actor a ``ProbabilisticActor`` over a
        ``TensorDictModule`` writing ``loc`` and ``scale``."""
        critics = loss.target_qvalue_network_params["module"]
        return _soft_value(loss, loss.actor_network, loss.qvalue_network.module, critics, 16, live)

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``E_a[min_i Q_i,target(s, a) - alpha log pi(a|s)]`` (:class:`SoftValue`), the
        actor and ``alpha`` as they are; with a shared encoder the critics read the target one."""
        critics = self.with_target_encoder(self.loss.target_qvalue_network_params)["module"]
        samples = self.cfg.value_samples
        return _soft_value(self.loss, self.actor, self.critic_module, critics, samples, live)


def _soft_value(loss: SACLoss, actor, critic: nn.Module, critics, samples: int, live: bool):
    """:class:`SoftValue` as a ``TensorDictModule`` over ``actor``'s observations: the actor's
    network with ``loss``'s actor parameters, ``critic`` with the stacked ``critics``, and
    ``loss``'s entropy coefficient (read in place with ``live``, else copies)."""
    network = actor[0]
    params = loss.actor_network_params["module", "0", "module"]
    module = SoftValue(
        with_params(network.module, params, live=live),
        critic,
        critics if live else critics.detach().clone(),
        loss.log_alpha if live else loss.log_alpha.detach().clone(),
        actor[1].distribution_kwargs,
        samples,
    )
    return TensorDictModule(module, in_keys=list(network.in_keys), out_keys=["state_value"])
