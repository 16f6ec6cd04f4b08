"""A 3-stage gymnasium env: a point robot visits two waypoints, then the goal.

Stage k heads for ``WAYPOINTS[k]``; reaching the goal (stage 2's waypoint) gives reward 1 and
ends the episode. The observation is ``(x, y, stage / 2)``; ``Waypoints-v0`` takes 4 discrete
moves, ``Waypoints-v0`` with ``continuous=True`` a 2-D velocity. ``start_stage=k`` starts
anywhere in the square inside stage k (the backward schedule's stage-k starts).
"""

import gymnasium as gym
import numpy as np
import torch

WAYPOINTS = np.array([[0.8, 0.2], [0.8, 0.8], [0.2, 0.8]], np.float32)
MOVES = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], np.float32)
RADIUS, SPEED = 0.1, 0.1


class Waypoints(gym.Env):
    num_stages = 3  # the task has as many stages (stages-train reads it)

    def __init__(self, continuous: bool = False, start_stage: int | None = None):
        self.observation_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)
        if continuous:
            self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        else:
            self.action_space = gym.spaces.Discrete(len(MOVES))
        self.continuous, self.start_stage = continuous, start_stage

    def _obs(self):
        return np.array([*self.pos, self.stage / 2], np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if self.start_stage is None:  # the task's own start: the corner, stage 0
            self.stage, self.pos = 0, np.array([0.2, 0.2], np.float32)
        else:  # anywhere in the square, inside stage k
            self.stage, self.pos = self.start_stage, self.np_random.uniform(0, 1, 2)
        return self._obs(), {}

    def step(self, action):
        move = np.clip(action, -1, 1) if self.continuous else MOVES[int(action)]
        self.pos = np.clip(self.pos + SPEED * move, 0.0, 1.0).astype(np.float32)
        reached = np.linalg.norm(self.pos - WAYPOINTS[self.stage]) < RADIUS
        done = bool(reached and self.stage == 2)
        self.stage += int(reached and not done)  # on to the next waypoint
        return self._obs(), float(done), done, False, {}


gym.register("Waypoints-v0", entry_point=Waypoints, max_episode_steps=100)


def waypoint_stage(td):
    """The stage of each state, from its observation: int64 ``[*batch, 1]``."""
    return (td["observation"][..., 2:3] * 2).round().to(torch.int64)
