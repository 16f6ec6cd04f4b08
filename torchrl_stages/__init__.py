"""torchrl-stages: Stacked Deep Q-Learning (SDQL) for multi-stage control on TorchRL."""

from torchrl_stages.experiment import Experiment
from torchrl_stages.learners import DDPGLearner, DQNLearner, Learner, TD3Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.rundir import load_policy, load_run
from torchrl_stages.schedule import train_backward
from torchrl_stages.stage import StageTrainer
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageTransform, freeze
from torchrl_stages.values import ActorCriticValue, QMaxValue

__all__ = [
    "ActorCriticValue",
    "DDPGLearner",
    "DQNLearner",
    "Experiment",
    "Learner",
    "QMaxValue",
    "StageTrainer",
    "StageTransform",
    "StackedPolicy",
    "StagedTask",
    "TD3Learner",
    "freeze",
    "load_policy",
    "load_run",
    "train_backward",
]
__version__ = "0.1.0"
