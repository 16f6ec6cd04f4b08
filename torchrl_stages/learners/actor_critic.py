"""What the deterministic actor-critic algorithms share: their keys and their learner base."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import TensorSpec
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import LossModule, ValueEstimators

from torchrl_stages.config import StageChecks, StageConfig
from torchrl_stages.learners.base import (
    FusedSoftUpdate,
    Learner,
    StageSpecs,
    check_loss_function,
    linear_schedule,
)
from torchrl_stages.learners.networks import SharedEncoderCritic, mlp
from torchrl_stages.values import with_params

SATURATION = 2.0  # pre-tanh magnitude beyond which `saturation_penalty` applies (tanh(2) = 0.96)


@dataclass
class ActorCriticConfig(StageConfig):
    """The keys of a deterministic actor-critic stage (continuous, bounded actions) with
    Gaussian exploration; ``lr`` is the critic's."""

    actor_lr: float = 1e-3
    loss_function: str = "l2"
    sigma_init: float = 0.5  # exploration noise std (in action units) at the start
    sigma_end: float = 0.1
    annealing_frames: int = 20_000
    # weight of mean(relu(|pre-tanh actor output| - 2)^2) in the actor loss: keeps the actor out
    # of deep tanh saturation, where its gradient vanishes and the actor stays at an action bound
    # for good (the manipulator's fine stage failed from one elbow configuration without it, the
    # cargo slider circled); zero inside |action| <= 0.96 of the bound (0: off)
    saturation_penalty: float = 1.0
    # one input encoder (the CNN of image observations) for the actor and the critic(s),
    # trained by the critic loss alone; the actor reads its features detached (as SAC-AE and
    # DrQ do). An update then encodes s and s' once each (s' with the target encoder) instead
    # of once per network (five with twin critics). A different network from separate
    # encoders. Without an image input or fourier_features there is no encoder to share.
    shared_encoder: bool = False


class ActorCriticLearner(Learner):
    """Deterministic actor + Q critic with Gaussian exploration; subclasses pick the loss.

    Subclasses implement :meth:`make_loss` and :meth:`update`; this class builds the actor
    (MLP + tanh squashing into the action bounds), the critic ``Q(s, a)``, the exploration
    module, the value estimator, the optimizers and the soft target updater.
    """

    action_spaces = ("continuous",)
    lr_keys = ("lr", "actor_lr")

    def __init__(self, cfg: ActorCriticConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        spec = specs.action_spec
        action_dim = spec.shape[-1]
        inputs, cells, fourier = specs.input_shapes, list(cfg.num_cells), cfg.fourier_features
        actor_net = mlp(inputs, action_dim, cells, fourier, self.cnn)
        self.actor = TensorDictSequential(
            TensorDictModule(actor_net, in_keys=specs.observation_keys, out_keys=["_actor_param"]),
            TanhModule(in_keys=["_actor_param"], out_keys=[specs.action_key], spec=spec),
        )
        # the critics read the actor's encoder when it is shared (and there is one to share)
        self.shared_encoder = bool(cfg.shared_encoder) and hasattr(actor_net, "encoder")
        self.critic = ValueOperator(
            SharedEncoderCritic(actor_net.encoder, action_dim, cells)
            if self.shared_encoder
            else mlp([*inputs, (action_dim,)], 1, cells, fourier, self.cnn),
            in_keys=[*specs.observation_keys, specs.action_key],
            out_keys=["state_action_value"],
        )
        self.noise = AdditiveGaussianModule(
            spec,
            sigma_init=float(cfg.sigma_init),
            sigma_end=float(cfg.sigma_end),
            annealing_num_steps=max(int(cfg.annealing_frames), 1),
            action_key=specs.action_key,
        )
        self.policy = self.actor
        self.exploration_policy = TensorDictSequential(self.actor, self.noise)
        self.loss = self.make_loss(cfg, spec)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = FusedSoftUpdate(self.loss, tau=cfg.tau)
        # the losses' networks: tensors in and out, the target actor reading the loss module's
        # target parameters (kept out of the module tree: no second copy in state_dict)
        low, high = spec.space.low, spec.space.high
        self.__dict__["_bounds"] = (low, high, bool((low != -1).any() or (high != 1).any()))
        target_actor = self.loss.target_actor_network_params.get(("module", "0", "module"))
        self.__dict__["_target_actor"] = with_params(self.actor_module, target_actor, live=True)
        actor_params, critic_params = self.loss_parameters()
        self.optimizers = {
            "actor": self.adam(actor_params, cfg.actor_lr),
            "critic": self.adam(critic_params, cfg.lr),
        }
        self.make_losses()

    @classmethod
    def validate(cls, checks: StageChecks) -> None:
        check_loss_function(checks)
        checks.positive("actor_lr", 1e-3)
        for field in ("saturation_penalty", "sigma_init", "sigma_end", "annealing_frames"):
            checks.non_negative(field)

    @property
    def actor_module(self) -> nn.Module:
        """The actor network: observation tensors in, the pre-tanh action out."""
        return self.actor[0].module

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
        encoder = self.loss.target_actor_network_params["module", "0", "module", "encoder"]
        out = critic_params.clone(recurse=False)
        out.set(("module", "encoder"), encoder.expand(critic_params.shape))
        return out

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
        return self.cfg.saturation_penalty * excess.pow(2).mean()

    def make_loss(self, cfg: ActorCriticConfig, spec: TensorSpec) -> LossModule:
        raise NotImplementedError

    def make_losses(self) -> None:
        """Sets up the loss functions the update runs: what the torchrl loss module computes,
        on plain tensors."""
        raise NotImplementedError

    def loss_parameters(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The loss module's trainable (actor, critic) parameters."""
        raise NotImplementedError

    def anneal_exploration(self, frames: int) -> None:
        cfg = self.cfg
        self.noise.sigma.fill_(
            linear_schedule(cfg.sigma_init, cfg.sigma_end, frames, cfg.annealing_frames)
        )
