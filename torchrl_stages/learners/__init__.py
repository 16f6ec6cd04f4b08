"""Per-stage learners: one class per algorithm behind the :class:`Learner` interface."""

import contextlib

import torch

from torchrl_stages.learners.base import FusedAdam, Learner, StageSpecs
from torchrl_stages.learners.ddpg import DDPGLearner
from torchrl_stages.learners.dqn import DQNLearner
from torchrl_stages.learners.td3 import TD3Learner

LEARNERS: dict[str, type[Learner]] = {
    cls.algo: cls for cls in (DQNLearner, DDPGLearner, TD3Learner)
}


def make_learner(
    cfg, specs: StageSpecs, compile: str = "off", device: str | torch.device | None = None
) -> Learner:
    """Builds the learner named by ``cfg.algo`` (``dqn``, ``ddpg`` or ``td3``); ``compile``:
    ``torch.compile`` mode of its update's loss (``off``, ``default``, ``reduce-overhead``...);
    ``device``: where every tensor it builds lives (networks, targets, bounds; default: torch's
    default device), the device of the envs it acts in."""
    with torch.device(device) if device is not None else contextlib.nullcontext():
        return LEARNERS[cfg.algo](cfg, specs, compile=compile)


__all__ = [
    "LEARNERS",
    "DDPGLearner",
    "DQNLearner",
    "FusedAdam",
    "Learner",
    "StageSpecs",
    "TD3Learner",
    "make_learner",
]
