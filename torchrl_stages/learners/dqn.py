"""DQN stage learner (discrete actions)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import TensorSpec
from torchrl.modules import EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate, ValueEstimators

from torchrl_stages.config import DQNConfig
from torchrl_stages.learners.base import Learner, StageSpecs, is_discrete, linear_schedule
from torchrl_stages.learners.networks import qvalue_net
from torchrl_stages.values import QMaxValue, with_params


class DQNLearner(Learner):
    """DQN (optionally double DQN) for one stage, on torchrl's ``DQNLoss``.

    Examples:
        >>> from torchrl.data import Categorical
        >>> from torchrl_stages.config import DQNConfig
        >>> from torchrl_stages.learners import DQNLearner, StageSpecs
        >>> specs = StageSpecs(["observation"], 2, "action", Categorical(4))
        >>> learner = DQNLearner(DQNConfig(gamma=0.9), specs)
        >>> learner.value().out_keys
        ['state_value']
    """

    algo = "dqn"

    def __init__(self, cfg: DQNConfig, specs: StageSpecs) -> None:
        super().__init__(cfg, specs)
        spec = specs.action_spec
        self.qnet = QValueActor(
            qvalue_net(
                specs.input_shapes,
                spec.space.n,
                list(cfg.num_cells),
                dueling=cfg.dueling,
                fourier=cfg.fourier_features,
                cnn=self.cnn,
            ),
            in_keys=specs.observation_keys,
            spec=spec,
            action_key=specs.action_key,
        )
        self.egreedy = EGreedyModule(
            spec,
            eps_init=float(cfg.eps_init),
            eps_end=float(cfg.eps_end),
            annealing_num_steps=max(int(cfg.annealing_frames), 1),
            action_key=specs.action_key,
        )
        self.policy = self.qnet
        self.exploration_policy = TensorDictSequential(self.qnet, self.egreedy)
        self.loss = DQNLoss(
            self.qnet,
            loss_function=cfg.loss_function,
            delay_value=True,
            double_dqn=cfg.double_dqn,
            action_space=spec,
        )
        self.loss.set_keys(action=specs.action_key)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.gamma)
        self.target_updater = SoftUpdate(self.loss, tau=cfg.tau)
        self.optimizers = {"qvalue": torch.optim.Adam(self.loss.parameters(), lr=cfg.lr)}

    @classmethod
    def check_action_spec(cls, spec: TensorSpec) -> str | None:
        if not is_discrete(spec):
            return (
                f"DQN needs a discrete action space (Categorical or OneHot), got "
                f"{type(spec).__name__}; use algo ddpg or td3 for this stage"
            )
        return None

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss = self.loss(batch)["loss"]
        self._check_losses(loss=loss)
        self._step(loss)
        self.target_updater.step()
        self.num_updates += 1
        return {"loss": loss.detach(), "grad_norm": self.grad_norms["qvalue"]}

    def anneal_exploration(self, frames: int) -> None:
        cfg = self.cfg
        self.egreedy.eps.fill_(
            linear_schedule(cfg.eps_init, cfg.eps_end, frames, cfg.annealing_frames)
        )

    def value(self, live: bool = False) -> TensorDictModuleBase:
        """``max_a Q_target(s, a)``."""
        target = self.loss.target_value_network_params
        return QMaxValue(with_params(self.qnet, target, live=live))
