"""Per-stage learners: one class per algorithm behind the :class:`Learner` interface."""

from torchrl_stages.learners.base import Learner, StageSpecs
from torchrl_stages.learners.ddpg import DDPGLearner
from torchrl_stages.learners.dqn import DQNLearner
from torchrl_stages.learners.td3 import TD3Learner

LEARNERS: dict[str, type[Learner]] = {
    cls.algo: cls for cls in (DQNLearner, DDPGLearner, TD3Learner)
}


def make_learner(cfg, specs: StageSpecs, compile: str = "off") -> Learner:
    """Builds the learner named by ``cfg.algo`` (``dqn``, ``ddpg`` or ``td3``); ``compile``:
    ``torch.compile`` mode of its fast update (``off``, ``default``, ``reduce-overhead``...)."""
    return LEARNERS[cfg.algo](cfg, specs, compile=compile)


__all__ = [
    "LEARNERS",
    "DDPGLearner",
    "DQNLearner",
    "Learner",
    "StageSpecs",
    "TD3Learner",
    "make_learner",
]
