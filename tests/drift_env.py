"""A small gymnasium env with long random episodes, for the resume tests: ``Drift-v0``.

A point drifts on a line: each step moves it by ``0.003 * (action - 1)`` plus a normal draw of
``self.np_random`` (standard deviation 0.003); reaching 1 gives reward 1 and ends the episode,
200 steps truncate it, and most random episodes run that long. Resets draw the start from
``self.np_random`` too: ``[0.2, 0.3)`` (stage 0, the task's starts) or ``[0.75, 0.85)`` (inside
stage 1). Stage 1 begins at 0.5. Every draw comes from ``self.np_random``, as gymnasium's
seeding API asks, so a resumed run rebuilds its episodes bitwise.

``Drift-v0`` with ``entropy=True`` draws its steps from a generator of its own, seeded by the
operating system: an env that does not follow the seeding API (what a resumed run warns about).

``stages-train`` imports this module through the env id ``drift_env:Drift-v0`` (with ``tests/``
on ``PYTHONPATH``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np

if TYPE_CHECKING:  # the async workers import this module: numpy and gymnasium only
    import torch
    from tensordict import TensorDictBase

MAX_STEPS = 200


class Drift(gym.Env):
    num_stages = 2

    def __init__(self, start_stage: int | None = None, entropy: bool = False) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 2.0, (1,), np.float32)
        self.action_space = gym.spaces.Discrete(3)  # 0: left, 1: stay, 2: right
        self.start_stage = start_stage
        self.entropy = np.random.default_rng() if entropy else None
        self.x = 0.0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        low = 0.2 if not self.start_stage else 0.75
        self.x = low + 0.1 * float(self.np_random.random())
        return np.array([self.x], np.float32), {}

    def step(self, action):
        rng = self.np_random if self.entropy is None else self.entropy
        self.x += 0.003 * (int(action) - 1) + 0.003 * float(rng.normal())
        done = self.x >= 1.0
        return np.array([self.x], np.float32), float(done), done, False, {}


gym.register("Drift-v0", entry_point=Drift, max_episode_steps=MAX_STEPS)


def drift_stage(td: TensorDictBase) -> torch.Tensor:
    """The stage function named in the config: 0 below 0.5, 1 from it on."""
    return (td["observation"][..., :1] >= 0.5).long()
