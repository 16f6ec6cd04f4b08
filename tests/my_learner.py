"""A learner of "the user's own package": a small Q-learner written against the Learner interface
alone, trained through ``+task.stages.<stage>.learner._target_=my_learner.TinyQLearner``.

It is registered nowhere and imports nothing of an algorithm of the package: a one-hidden-layer
Q-network, its target copy moved by ``tau``, epsilon-greedy exploration, ``max_a Q_target`` as
the value it hands to the stage before it.
"""

from __future__ import annotations

import copy

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.modules import EGreedyModule, QValueActor

from torchrl_stages.learners import Learner, StageSpecs
from torchrl_stages.learners.ops import linear_schedule
from torchrl_stages.values import QMaxValue


class TinyQLearner(Learner):
    algo = "tiny_q"  # a name for its messages; it is not a registered algorithm
    action_spaces = ("discrete",)

    def __init__(self, cfg, specs: StageSpecs, *, compile: str = "off", hidden: int = 32) -> None:
        super().__init__(cfg, specs, compile=compile)
        actions = specs.action_spec.space.n
        self.q = nn.Sequential(
            nn.Linear(specs.observation_dim, hidden), nn.ReLU(), nn.Linear(hidden, actions)
        )
        self.target_q = copy.deepcopy(self.q).requires_grad_(False)
        keys = dict(in_keys=specs.observation_keys, spec=specs.action_spec)
        self.policy = QValueActor(self.q, action_key=specs.action_key, **keys)
        self.egreedy = EGreedyModule(
            specs.action_spec, eps_init=1.0, eps_end=0.05, action_key=specs.action_key
        )
        self.exploration_policy = TensorDictSequential(self.policy, self.egreedy)
        self.optimizers = {"q": torch.optim.Adam(self.q.parameters(), lr=self.cfg.lr)}

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        obs = torch.cat(self.inputs(batch), -1)
        q = self.q(obs).gather(-1, batch.get(self.specs.action_key).reshape(-1, 1))
        with torch.no_grad():
            nxt = batch.get("next")
            q_next = self.target_q(torch.cat(self.inputs(batch, nxt=True), -1)).amax(-1, True)
            alive = (~nxt.get("terminated")).to(q.dtype)
            target = nxt.get("reward") + self.cfg.gamma * alive * q_next
        loss = (q - target).pow(2).mean()
        self._check_losses(loss=loss)
        self._step(loss)
        with torch.no_grad():
            for t, p in zip(self.target_q.parameters(), self.q.parameters(), strict=True):
                t.lerp_(p, self.cfg.tau)
        self.num_updates += 1
        return {"loss": loss.detach()}

    def anneal_exploration(self, frames: int) -> None:
        self.egreedy.eps.fill_(linear_schedule(1.0, 0.05, frames, self.cfg.frames // 2))

    def value(self, live: bool = False) -> TensorDictModuleBase:
        target = self.target_q if live else copy.deepcopy(self.target_q)
        actor = QValueActor(
            target, in_keys=self.specs.observation_keys, spec=self.specs.action_spec
        )
        return QMaxValue(actor)
