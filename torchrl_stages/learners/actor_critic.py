"""What the actor-critic learners share: an actor and ``Q(s, a)`` critics in the torchrl loss
module, optionally one input encoder for both; a learned entropy coefficient (SAC, discrete SAC)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator

from torchrl_stages.config import StageConfig
from torchrl_stages.config.bounds import flag, non_negative, one_of, positive
from torchrl_stages.learners.base import LOSS_FUNCTIONS, Learner, StageSpecs
from torchrl_stages.learners.networks import SharedEncoderCritic
from torchrl_stages.learners.ops import stacked_calls
from torchrl_stages.learners.stacking import per_seed, seed_rows
from torchrl_stages.values import ActorCriticValue, with_params

SATURATION = 2.0  # pre-tanh magnitude beyond which `saturation_penalty` applies (tanh(2) = 0.96)


@dataclass
class ActorCriticConfig(StageConfig):
    """The keys of an actor-critic stage (continuous, bounded actions); ``lr`` is the critic's."""

    actor_lr: float = positive(1e-3)
    loss_function: str = one_of(*LOSS_FUNCTIONS, default="l2")
    # one input encoder (CNN, fourier_features) for the actor and critic(s), trained by the
    # critic loss alone, the actor reading its features detached (as SAC-AE and DrQ do); off
    # without an image input or fourier_features
    shared_encoder: bool = flag(False)


@dataclass
class DeterministicActorCriticConfig(ActorCriticConfig):
    """The keys of a deterministic actor-critic stage with Gaussian exploration."""

    sigma_init: float = non_negative(0.5)  # exploration noise std (in action units) at the start
    sigma_end: float = non_negative(0.1)
    # weight of mean(relu(|pre-tanh actor output| - 2)^2) in the actor loss: keeps the actor out
    # of deep tanh saturation, where its gradient vanishes (0: off)
    saturation_penalty: float = non_negative(1.0)


class ActorCriticLearner(Learner):
    """An actor and ``Q(s, a)`` critics, the parameters in the torchrl loss module: subclasses
    implement ``make_actor(net, spec)`` and ``_plain_losses(batch)``."""

    action_spaces = ("continuous",)
    lr_keys = ("lr", "actor_lr")
    ACTOR_PATH: tuple[str, ...] = ("module", "0", "module")  #: the actor network in the loss
    CRITIC = "qvalue_network"  #: the loss module's name of its critic (twin critics)
    ACTOR_OUTPUTS = 1  #: the actor network's outputs per action dimension

    def __init__(self, cfg: ActorCriticConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        spec = specs.action_spec
        action_dim = spec.shape[-1]
        actor_net = self.network(self.ACTOR_OUTPUTS * action_dim)
        self.__dict__["actor_module"] = actor_net  # obs in, e.g. the pre-tanh action out
        self.actor = self.make_actor(actor_net, spec)
        self.shared_encoder = bool(cfg.shared_encoder) and hasattr(actor_net, "encoder")
        if self.shared_encoder:
            critic = SharedEncoderCritic(actor_net.encoder, action_dim, list(cfg.num_cells))
        else:
            critic = self.network(1, (action_dim,))
        keys = [*specs.observation_keys, specs.action_key]
        self.critic = ValueOperator(critic, in_keys=keys, out_keys=["state_action_value"])
        # the critic network (observation and action tensors in, Q(s, a) out), and its part
        # after a shared encoder (the whole critic without one); not registered twice
        net = critic.body if self.shared_encoder else critic
        self.__dict__.update(critic_module=critic, critic_net=net)
        self.policy = self.actor
        self.exploration_policy = self.make_exploration()
        loss = self.torchrl_loss(
            self.actor, self.critic, loss_function=cfg.loss_function, **self.loss_kwargs(cfg)
        )
        if self.shared_encoder:  # the critics read the (target) actor's encoder, not copies
            for name in (f"{self.CRITIC}_params", f"target_{self.CRITIC}_params"):
                del loss._modules[name]["module", "encoder"]  # _modules: no updater warning
        self.use_loss(loss)
        # the target actor reads the loss's target parameters (not a second state_dict copy)
        if self.loss.target_actor_network_params is not None:
            target_actor = self.loss.target_actor_network_params.get(self.ACTOR_PATH)
            self.__dict__["_target_actor"] = with_params(actor_net, target_actor, live=True)
        actor_params, critic_params = self.loss_parameters()
        self.optimizers = {
            "actor": self.adam(actor_params, cfg.actor_lr),
            "critic": self.adam(critic_params, cfg.lr),
        }
        self.make_losses()

    def loss_kwargs(self, cfg: ActorCriticConfig) -> dict:
        """:attr:`torchrl_loss`'s other keyword arguments: twin critics, their targets delayed;
        a shared encoder's copies in the critics are views of the actor's."""
        return {
            "action_spec": self.specs.action_spec,
            "num_qvalue_nets": 2,
            "delay_qvalue": True,
            "separate_losses": self.shared_encoder,
        }

    def make_losses(self) -> None:
        self._losses = self.compiled(self._plain_losses)

    def make_exploration(self) -> TensorDictModuleBase:
        return self.actor

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The (actor, critic) optimizers' parameters; a shared encoder is the critic's."""
        actor = self.loss.actor_network_params.flatten_keys(".")
        critic = getattr(self.loss, f"{self.CRITIC}_params").flatten_keys(".")
        encoder = [k for k in actor.keys() if self.shared_encoder and ".encoder." in f".{k}"]
        actor_params = [p for k, p in actor.items() if k not in encoder]
        return actor_params, [*critic.values(), *(actor[k] for k in encoder)]

    def target_critics(self) -> TensorDictBase:
        """The loss's target critic parameters, with a shared encoder the target actor's."""
        critic_params = getattr(self.loss, f"target_{self.CRITIC}_params")
        if not self.shared_encoder:
            return critic_params
        encoder = self.loss.target_actor_network_params[(*self.ACTOR_PATH, "encoder")]
        out = critic_params.clone(recurse=False)
        out.set(("module", "encoder"), encoder.expand(critic_params.shape))
        return out

    def features(self, obs: list[torch.Tensor], target: bool = False) -> list[torch.Tensor]:
        """The shared encoder's features of ``obs`` (the target's with ``target``), else ``obs``."""
        if not self.shared_encoder:
            return obs
        return [(self._target_actor if target else self.actor_module).encoder(*obs)]

    def actor_head(self, features: list[torch.Tensor], target: bool = False) -> torch.Tensor:
        """The (target) actor network's output on :meth:`features`."""
        net = self._target_actor if target else self.actor_module
        return (net.body if self.shared_encoder else net)(*features)

    def critic_inputs(self, features: list[torch.Tensor], action: torch.Tensor) -> tuple:
        """What :meth:`critic_net` reads: :meth:`features` and the action."""
        if self.shared_encoder:
            return (torch.cat([*features, action], -1),)
        return (*features, action)

    def critic_values(
        self, params: TensorDictBase, features, action, detach: bool = False, count=None
    ) -> list[torch.Tensor]:
        """``Q_i(s, a)`` of each critic (the first ``count``) of the loss ``params`` on
        :meth:`features`; ``detach``: no gradient to ``params``."""
        params = params["module", "body"] if self.shared_encoder else params["module"]
        inputs = self.critic_inputs(features, action)
        return stacked_calls(self.critic_net, params, *inputs, detach=detach, count=count)


class DeterministicActorCriticLearner(ActorCriticLearner):
    """A tanh actor into the action bounds with Gaussian exploration noise and a penalty on
    tanh saturation (DDPG, TD3)."""

    def make_actor(self, actor_net: nn.Module, spec: TensorSpec) -> TensorDictModuleBase:
        low, high = spec.space.low, spec.space.high  # the TanhModule's, for squash
        self.__dict__["_bounds"] = (low, high, bool((low != -1).any() or (high != 1).any()))
        keys = self.specs
        return TensorDictSequential(
            TensorDictModule(actor_net, in_keys=keys.observation_keys, out_keys=["_actor_param"]),
            TanhModule(in_keys=["_actor_param"], out_keys=[keys.action_key], spec=spec),
        )

    def make_exploration(self) -> TensorDictModuleBase:
        cfg = self.cfg
        self.noise = self.exploration_module(AdditiveGaussianModule, cfg.sigma_init, cfg.sigma_end)
        return TensorDictSequential(self.actor, self.noise)

    def squash(self, u: torch.Tensor) -> torch.Tensor:
        """The actor's ``TanhModule``: tanh into the action bounds."""
        low, high, scaled = self._bounds
        action = u.tanh()
        return low + (high - low) * (action + 1) / 2 if scaled else action

    def penalty(self, u: torch.Tensor) -> torch.Tensor | float:
        """``cfg.saturation_penalty`` times the mean of ``relu(|u| - SATURATION)^2``."""
        if self.cfg.saturation_penalty <= 0:
            return 0.0
        excess = (u.abs() - SATURATION).clamp_min(0.0)
        return self.cfg.saturation_penalty * self.batch_mean(excess.pow(2))

    def anneal_exploration(self, frames: int) -> None:
        self.anneal_noise(self.noise.sigma, self.cfg.sigma_init, self.cfg.sigma_end, frames)

    @classmethod
    def value_from_loss(cls, loss, live: bool = False, critics=None) -> ActorCriticValue:
        """``min_i Q_i,target(s, mu_target(s))`` of the loss's target networks, a critic per row
        of stacked ``critics`` (default: the loss's target critic parameters)."""
        if critics is None:
            critics = getattr(loss, f"target_{cls.CRITIC}_params")
        rows = [critics[i] for i in range(critics.shape[0])] if critics.batch_dims else [critics]
        return ActorCriticValue(
            with_params(loss.actor_network, loss.target_actor_network_params, live=live),
            [with_params(getattr(loss, cls.CRITIC), params, live=live) for params in rows],
        )

    def value(self, live: bool = False) -> TensorDictModuleBase:
        return self.value_from_loss(self.loss, live, self.target_critics())


class EntropyRegularized:
    """A :class:`~torchrl_stages.learners.Learner` mixin: ``loss.log_alpha`` (one per seed) and
    ``_losses(batch)``, the actor's, critics' and alpha's losses, stepped together."""

    lr_keys = ("lr", "actor_lr", "alpha_lr")

    def learn_alpha(self) -> None:
        """Adds the ``alpha`` optimizer of ``log_alpha``, one per seed (``[N]``) if seed-stacked."""
        if self.seeds is not None:
            log_alpha = self.loss.log_alpha.detach()
            self.loss.log_alpha = nn.Parameter(log_alpha.expand(self.seeds).clone())
        self.optimizers["alpha"] = self.adam([self.loss.log_alpha], self.cfg.alpha_lr)

    def alpha(self, like: torch.Tensor) -> torch.Tensor:
        """The entropy coefficient, detached, shaped to broadcast against ``like``."""
        return per_seed(seed_rows(self.loss.log_alpha).detach().exp(), like)

    def alpha_loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        """``-log_alpha (log pi + target_entropy)`` over the batch."""
        entropy_gap = log_prob.detach() + self.loss.target_entropy
        log_alpha = per_seed(seed_rows(self.loss.log_alpha), entropy_gap)
        return self.batch_mean(-log_alpha * entropy_gap)

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss_actor, loss_q, loss_alpha = self._losses(batch)
        losses = {"loss_actor": loss_actor, "loss_qvalue": loss_q, "loss_alpha": loss_alpha}
        out = self._optimize(losses, loss_actor + loss_q + loss_alpha)
        self.num_updates += 1
        out["alpha"] = seed_rows(self.loss.log_alpha).detach().exp().clone()
        norms = self.grad_norms
        return {**out, "grad_norm_actor": norms["actor"], "grad_norm_critic": norms["critic"]}

    def anneal_exploration(self, frames: int) -> None:
        """Nothing to anneal: the entropy coefficient is learned."""

    @staticmethod
    def soft_value(module: type[nn.Module], loss, critics, live: bool, *args) -> TensorDictModule:
        """``module`` (a soft value) of ``loss``'s actor, its critic with the ``critics``
        parameters and ``log_alpha`` (read in place with ``live``, else copies) as a
        ``TensorDictModule``."""
        network, log_alpha = loss.actor_network[0], loss.log_alpha
        if not live:
            critics, log_alpha = critics.detach().clone(), log_alpha.detach().clone()
        params = loss.actor_network_params["module", "0", "module"]
        actor = with_params(network.module, params, live=live)
        value = module(actor, loss.qvalue_network.module, critics, log_alpha, *args)
        return TensorDictModule(value, in_keys=list(network.in_keys), out_keys=["state_value"])
