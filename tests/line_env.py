"""A small gymnasium env for the bring-your-own-env tests, registered as ``LineWorld-v0``.

A point on the segment [0, 1] moves left or right by 1/8 per step; reaching 1 gives reward 1 and
ends the episode (20 steps truncate). Stage 0 is the left half, stage 1 from x = 0.5 on. The env
takes ``start_stage`` (None: start at 0; k: a random cell of stage k), so it trains with the
backward schedule (``task.stage_starts=true``) as well as with the joint one. With ``pit=True``
a step left from 0 falls in a pit: the episode terminates, failed; every step then reports
``info["is_success"]`` (an env whose terminations are not all successes).

``stages-train`` imports this module through the env id ``line_env:LineWorld-v0`` (with
``tests/`` on ``PYTHONPATH``), as a user's package would register its own env.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import GymEnv

STEP = 0.125


class LineWorld(gym.Env):
    num_stages = 2

    def __init__(self, start_stage: int | None = None, pit: bool = False) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, (1,), np.float32)
        self.action_space = gym.spaces.Discrete(2)  # 0: left, 1: right
        self.start_stage = start_stage
        self.pit = pit
        self.x = 0.0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if self.start_stage is None:
            self.x = 0.0
        else:  # one of the 4 cells of the stage
            self.x = 0.5 * self.start_stage + STEP * float(self.np_random.integers(0, 4))
        return np.array([self.x], np.float32), {}

    def step(self, action):
        move = STEP if int(action) == 1 else -STEP
        fell = self.pit and self.x + move < 0.0
        self.x = float(np.clip(self.x + move, 0.0, 1.0))
        done = self.x >= 1.0
        info = {"is_success": done} if self.pit else {}
        return np.array([self.x], np.float32), float(done), done or fell, False, info


gym.register("LineWorld-v0", entry_point=LineWorld, max_episode_steps=20)


def line_stage(td: TensorDictBase) -> torch.Tensor:
    """The stage function named in the config: 0 left of the middle, 1 from it on."""
    return (td["observation"][..., :1] >= 0.5).long()


def unbatched_line(batch_size=None, device="cpu"):
    """A factory that ignores the batch size it is asked for (a protocol error)."""
    env = GymEnv("LineWorld-v0", categorical_action_encoding=True, device=device)
    env.num_stages = 2
    env.stage_fn = line_stage
    return env
