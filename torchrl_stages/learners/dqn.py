"""DQN (double, dueling, advantage learning) for discrete-action stages."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import OneHot
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss
from torchrl.objectives.utils import distance_loss

from torchrl_stages.config import StageConfig
from torchrl_stages.config.bounds import flag, free, in_range, one_of
from torchrl_stages.learners.base import LOSS_FUNCTIONS, Learner, StageSpecs, register_algorithm
from torchrl_stages.learners.ops import taken, td0_target
from torchrl_stages.values import QMaxValue, with_params


@dataclass
class DQNConfig(StageConfig):
    """DQN stage (discrete actions): ``DQNLoss``'s objective with an epsilon-greedy collector."""

    algo: str = free("dqn")
    double_dqn: bool = flag(True)  # double-DQN targets (torchrl's DQNLoss(double_dqn=...))
    # dueling Q-network: separate state-value and advantage heads, so that small differences
    # between actions are not lost in the value
    dueling: bool = flag(True)
    loss_function: str = one_of(*LOSS_FUNCTIONS, default="l2")
    # advantage learning (Bellemare et al. 2016): the target y - alpha (max_b Q_target(s, b) -
    # Q_target(s, a)) widens action gaps about 1 / (1 - alpha), keeping max_a Q; 0: plain DQN
    advantage_learning: float = in_range(0, 1, 0.0, high_open=True)
    eps_init: float = in_range(0, 1, 1.0)
    eps_end: float = in_range(0, 1, 0.05)  # epsilon decays linearly to it over `annealing_frames`


@register_algorithm
class DQNLearner(Learner):
    """DQN for one stage: parameters and targets in torchrl's ``DQNLoss``, the update on plain
    tensors.

    Examples:
        >>> from torchrl.data import Categorical
        >>> specs = StageSpecs(["observation"], 2, "action", Categorical(4))
        >>> DQNLearner(DQNConfig(gamma=0.9), specs).value().out_keys
        ['state_value']
    """

    algo = "dqn"
    Config = DQNConfig
    action_spaces = ("discrete",)
    torchrl_loss = DQNLoss
    stacks_seeds = True

    def __init__(self, cfg: DQNConfig, specs: StageSpecs, *, compile: str = "off") -> None:
        super().__init__(cfg, specs, compile=compile)
        spec, key = specs.action_spec, specs.action_key
        net = self.network(spec.space.n, dueling=cfg.dueling)
        self.__dict__["q_module"] = net  # obs in, one Q-value per action out
        self.qnet = QValueActor(net, in_keys=specs.observation_keys, spec=spec, action_key=key)
        self.egreedy = self.exploration_module(EGreedyModule, cfg.eps_init, cfg.eps_end)
        self.policy = self.qnet
        self.exploration_policy = TensorDictSequential(self.qnet, self.egreedy)
        loss = DQNLoss(
            self.qnet,
            loss_function=cfg.loss_function,
            delay_value=True,
            double_dqn=cfg.double_dqn,
            action_space=spec,
        )
        self.use_loss(loss)
        self.optimizers = {"qvalue": self.adam(self.loss.parameters(), cfg.lr)}
        # the target network reads the loss's target parameters (not a second state_dict copy)
        target = self.loss.target_value_network_params.get(("module", "0", "module"))
        self.__dict__["_target_q"] = with_params(self.q_module, target, live=True)
        self._loss_fn = self.compiled(self._plain_loss)

    @classmethod
    def value_from_loss(cls, loss: DQNLoss, live: bool = False) -> TensorDictModuleBase:
        """``max_a Q_target(s, a)``."""
        target = with_params(loss.value_network, loss.target_value_network_params, live=live)
        return QMaxValue(target)

    def _plain_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """``DQNLoss``; with ``advantage_learning`` (alpha) the target less
        ``alpha (max_b Q_target(s, b) - Q_target(s, a))``."""
        obs = self.inputs(batch)
        action = batch.get(self.specs.action_key)
        one_hot = isinstance(self.specs.action_spec, OneHot)
        pred = taken(self.q_module(*obs), action, one_hot)
        with torch.no_grad():
            next_obs = self.inputs(batch, nxt=True)
            q_next = self._target_q(*next_obs)
            if self.cfg.double_dqn:
                next_value = q_next.gather(-1, self.q_module(*next_obs).argmax(-1, keepdim=True))
            else:
                next_value = q_next.max(-1, keepdim=True).values
            target = td0_target(batch, next_value, self.cfg.gamma)
            if self.cfg.advantage_learning:
                q_target = self._target_q(*obs)
                gap = q_target.max(-1, keepdim=True).values - taken(q_target, action, one_hot)
                target = target - self.cfg.advantage_learning * gap
        return self.batch_mean(distance_loss(pred, target, self.cfg.loss_function))

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self._loss_fn(batch)
        out = self._optimize({"loss": loss}, loss)
        self.num_updates += 1
        return {**out, "grad_norm": self.grad_norms["qvalue"]}

    def anneal_exploration(self, frames: int) -> None:
        self.anneal_noise(self.egreedy.eps, self.cfg.eps_init, self.cfg.eps_end, frames)

    def value(self, live: bool = False) -> TensorDictModuleBase:
        return self.value_from_loss(self.loss, live=live)
