"""torchrl-stages: Stacked Deep Q-Learning (SDQL) for multi-stage control on TorchRL."""

from torchrl_stages.gym_env import GymStageEnv, threshold_stage
from torchrl_stages.learners import (
    ALGORITHMS,
    Learner,
    StageSpecs,
    make_learner,
    register_algorithm,
)
from torchrl_stages.loss_value import value_from_loss
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.loading import load_policy, load_run
from torchrl_stages.schedules import train_backward, train_stage
from torchrl_stages.stage import StageTrainer
from torchrl_stages.sweeps import summarize_sweep
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageRewardTransform, StageTransform, freeze
from torchrl_stages.values import ActorCriticValue, QMaxValue, with_params

__all__ = [
    "ALGORITHMS",
    "ActorCriticValue",
    "Experiment",
    "GymStageEnv",
    "Learner",
    "QMaxValue",
    "StageRewardTransform",
    "StageSpecs",
    "StageTrainer",
    "StageTransform",
    "StackedPolicy",
    "StagedTask",
    "freeze",
    "load_policy",
    "load_run",
    "make_learner",
    "register_algorithm",
    "summarize_sweep",
    "value_from_loss",
    "threshold_stage",
    "train_backward",
    "train_stage",
    "with_params",
]
__version__ = "0.1.0"
