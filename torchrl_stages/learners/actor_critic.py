"""What the actor-critic algorithms share: their keys and their learner bases.

:class:`ActorCriticLearner` holds an actor, a ``Q(s, a)`` critic (twin ones through the torchrl
loss module that keeps the parameters), optionally one input encoder shared by both, the
optimizers and the soft target updater; :class:`DeterministicActorCriticLearner` adds a
deterministic tanh actor with Gaussian exploration.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import LossModule, ValueEstimators

from torchrl_stages.config import StageChecks, StageConfig
from torchrl_stages.config.bounds import flag, non_negative, one_of, positive
from torchrl_stages.learners.base import (
    LOSS_FUNCTIONS,
    Learner,
    StageSpecs,
    check_loss_function,
)
from torchrl_stages.learners.networks import SharedEncoderCritic, mlp
from torchrl_stages.learners.ops import FusedSoftUpdate, linear_schedule, stacked_calls
from torchrl_stages.values import with_params

SATURATION = 2.0  # pre-tanh magnitude beyond which `saturation_penalty` applies (tanh(2) = 0.96)


@dataclass
class ActorCriticConfig(StageConfig):
    """The keys of an actor-critic stage (continuous, bounded actions); ``lr`` is the critic's."""

    actor_lr: float = positive(1e-3)
    loss_function: str = one_of(*LOSS_FUNCTIONS, default="l2")
    # one input encoder (the CNN of image observations) for the actor and the critic(s),
    # trained by the critic loss alone; the actor reads its features detached (as SAC-AE and
    # DrQ do). An update then encodes s and s' once each (s' with the target encoder) instead
    # of once per network (five with twin critics). A different network from separate
    # encoders. Without an image input or fourier_features there is no encoder to share.
    shared_encoder: bool = flag(False)


@dataclass
class DeterministicActorCriticConfig(ActorCriticConfig):
    """The keys of a deterministic actor-critic stage with Gaussian exploration."""

    sigma_init: float = non_negative(0.5)  # exploration noise std (in action units) at the start
    sigma_end: float = non_negative(0.1)
    # weight of mean(relu(|pre-tanh actor output| - 2)^2) in the actor loss: keeps the actor out
    # of deep tanh saturation, where its gradient vanishes and the actor stays at an action bound
    # for good (the manipulator's fine stage failed from one elbow configuration without it, the
    # cargo slider circled); zero inside |action| <= 0.96 of the bound (0: off)
    saturation_penalty: float = non_negative(1.0)


class ActorCriticLearner(Learner):
    """An actor and a ``Q(s, a)`` critic; subclasses pick the actor, exploration and loss.

    Subclasses implement :meth:`make_actor`, :meth:`make_loss`, :meth:`make_losses` and
    :meth:`update`; this class builds the actor network, the critic, the value estimator,
    the optimizers and the soft target updater, and shares an input encoder when asked.
    """

    action_spaces = ("continuous",)
    lr_keys = ("lr", "actor_lr")
    #: where the actor network's parameters sit in the loss module's actor parameters
    ACTOR_PATH: tuple[str, ...] = ("module", "0", "module")
    #: the loss module's name of its critic (``qvalue_network``: twin critics)
    CRITIC = "qvalue_network"

    def __init__(self, cfg: ActorCriticConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        spec = specs.action_spec
        action_dim = spec.shape[-1]
        inputs, cells, fourier = specs.input_shapes, list(cfg.num_cells), cfg.fourier_features
        actor_net = mlp(inputs, self.actor_outputs(action_dim), cells, fourier, self.cnn)
        self.__dict__["_actor_net"] = actor_net  # a sub-module of self.actor, not a second one
        self.actor = self.make_actor(actor_net, spec)
        # the critics read the actor's encoder when it is shared (and there is one to share)
        self.shared_encoder = bool(cfg.shared_encoder) and hasattr(actor_net, "encoder")
        self.critic = ValueOperator(
            SharedEncoderCritic(actor_net.encoder, action_dim, cells)
            if self.shared_encoder
            else mlp([*inputs, (action_dim,)], 1, cells, fourier, self.cnn),
            in_keys=[*specs.observation_keys, specs.action_key],
            out_keys=["state_action_value"],
        )
        self.policy = self.actor
        self.exploration_policy = self.make_exploration()
        self.loss = self.make_loss(cfg, spec)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = FusedSoftUpdate(self.loss, tau=cfg.tau)
        # the losses' networks: tensors in and out, the target actor reading the loss module's
        # target parameters (kept out of the module tree: no second copy in state_dict)
        if self.loss.target_actor_network_params is not None:
            target_actor = self.loss.target_actor_network_params.get(self.ACTOR_PATH)
            self.__dict__["_target_actor"] = with_params(actor_net, target_actor, live=True)
        actor_params, critic_params = self.loss_parameters()
        self.optimizers = {
            "actor": self.adam(actor_params, cfg.actor_lr),
            "critic": self.adam(critic_params, cfg.lr),
        }
        self.make_losses()

    def actor_outputs(self, action_dim: int) -> int:
        """How many numbers the actor network outputs per state."""
        return action_dim

    def make_actor(self, actor_net: nn.Module, spec: TensorSpec) -> TensorDictModuleBase:
        """The policy module around the actor network (greedy in deterministic mode)."""
        raise NotImplementedError

    def make_exploration(self) -> TensorDictModuleBase:
        """The policy the collector runs."""
        return self.actor

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        check_loss_function(checks)
        checks.positive("actor_lr", 1e-3)

    @property
    def actor_module(self) -> nn.Module:
        """The actor network: observation tensors in, its outputs (e.g. the pre-tanh action)
        out."""
        return self._actor_net

    @property
    def critic_module(self) -> nn.Module:
        """The critic network: observation and action tensors in, ``Q(s, a)`` out."""
        return self.critic.module

    def drop_critic_encoder_copies(self, loss: LossModule, critic: str) -> None:
        """With a shared encoder, removes the loss module's copies of it from the ``critic``
        parameters and their targets: torchrl keeps them as views without gradient (and target
        copies its updater does not move); the critics read the (target) actor's encoder."""
        if self.shared_encoder:
            for name in (f"{critic}_params", f"target_{critic}_params"):
                del loss._modules[name]["module", "encoder"]  # _modules: no updater warning yet

    def split_parameters(
        self, actor: TensorDictBase, critic: TensorDictBase
    ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The (actor, critic) optimizers' parameters: a shared encoder goes to the critic's."""
        actor, critic = actor.flatten_keys("."), critic.flatten_keys(".")
        if not self.shared_encoder:
            return list(actor.values()), list(critic.values())
        encoder = [k for k in actor.keys() if ".encoder." in f".{k}"]
        return (
            [p for k, p in actor.items() if k not in encoder],
            [*critic.values(), *(actor[k] for k in encoder)],
        )

    def with_target_encoder(self, critic_params: TensorDictBase) -> TensorDictBase:
        """Target critic parameters, with a shared encoder the target actor's (for modules
        that run the whole critic, such as the stage value)."""
        if not self.shared_encoder:
            return critic_params
        encoder = self.loss.target_actor_network_params[(*self.ACTOR_PATH, "encoder")]
        out = critic_params.clone(recurse=False)
        out.set(("module", "encoder"), encoder.expand(critic_params.shape))
        return out

    def critic_values(self, params, *inputs: torch.Tensor, module=None) -> list[torch.Tensor]:
        """``Q_i(inputs)`` of every critic in the stacked ``params`` (``[num_critics, ...]``),
        through ``module`` (default: the whole critic)."""
        return stacked_calls(self.critic_module if module is None else module, params, *inputs)

    def head_values(self, params, features: torch.Tensor, action: torch.Tensor) -> list:
        """``Q_i`` of every critic head in the stacked ``params`` on shared-encoder features."""
        x = torch.cat([features, action], -1)
        return self.critic_values(params, x, module=self.critic_module.body)

    def make_loss(self, cfg: ActorCriticConfig, spec: TensorSpec) -> LossModule:
        raise NotImplementedError

    def make_losses(self) -> None:
        """Sets up the loss functions the update runs: what the torchrl loss module computes,
        on plain tensors."""
        raise NotImplementedError

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The loss module's trainable (actor, critic) parameters."""
        critic = getattr(self.loss, f"{self.CRITIC}_params")
        return self.split_parameters(self.loss.actor_network_params, critic)

    def with_action_key(self, loss: LossModule) -> LossModule:
        """``loss`` reading the stage's action entry, without copies of a shared encoder."""
        loss.set_keys(action=self.specs.action_key)
        self.drop_critic_encoder_copies(loss, self.CRITIC)
        return loss


class DeterministicActorCriticLearner(ActorCriticLearner):
    """A deterministic actor (MLP + tanh squashing into the action bounds) with Gaussian
    exploration noise, and the saturation penalty that keeps it out of the tanh's flat ends."""

    def __init__(
        self, cfg: DeterministicActorCriticConfig, specs: StageSpecs, *, compile: str = "off"
    ) -> None:
        low, high = specs.action_spec.space.low, specs.action_spec.space.high
        self.__dict__["_bounds"] = (low, high, bool((low != -1).any() or (high != 1).any()))
        super().__init__(cfg, specs, compile=compile)

    def make_actor(self, actor_net: nn.Module, spec: TensorSpec) -> TensorDictModuleBase:
        keys = self.specs
        return TensorDictSequential(
            TensorDictModule(actor_net, in_keys=keys.observation_keys, out_keys=["_actor_param"]),
            TanhModule(in_keys=["_actor_param"], out_keys=[keys.action_key], spec=spec),
        )

    def make_exploration(self) -> TensorDictModuleBase:
        cfg = self.cfg
        self.noise = AdditiveGaussianModule(
            self.specs.action_spec,
            sigma_init=float(cfg.sigma_init),
            sigma_end=float(cfg.sigma_end),
            annealing_num_steps=max(int(cfg.annealing_frames), 1),
            action_key=self.specs.action_key,
        )
        return TensorDictSequential(self.actor, self.noise)

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        super().validate(checks)
        for field in ("saturation_penalty", "sigma_init", "sigma_end", "annealing_frames"):
            checks.non_negative(field)

    def squash(self, u: torch.Tensor) -> torch.Tensor:
        """The actor's tanh into the action bounds (what its ``TanhModule`` does)."""
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
        cfg = self.cfg
        self.noise.sigma.fill_(
            linear_schedule(cfg.sigma_init, cfg.sigma_end, frames, cfg.annealing_frames)
        )
