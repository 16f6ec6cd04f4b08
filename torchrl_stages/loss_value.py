"""``V(s)`` from a torchrl loss module, for a drop-in training loop built on torchrl's losses."""

from __future__ import annotations

from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import LossModule

from torchrl_stages.learners import ALGORITHMS

__all__ = ["value_from_loss"]


def value_from_loss(loss: LossModule, *, live: bool = False) -> TensorDictModuleBase:
    """The frozen ``V(s)`` (``"state_value"``) of stage k+1 from the target networks of its
    torchrl loss, for ``StageTransform(next_value=...)``; ``live`` reads the targets in place.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.modules import QValueActor
        >>> from torchrl.objectives import DQNLoss, SoftUpdate
        >>> qnet = QValueActor(torch.nn.Linear(2, 3), action_space="categorical")
        >>> loss = DQNLoss(qnet, action_space="categorical", delay_value=True)
        >>> updater = SoftUpdate(loss, tau=0.05)  # the target networks' updater
        >>> value = value_from_loss(loss)
        >>> value(TensorDict(observation=torch.zeros(5, 2), batch_size=[5]))["state_value"].shape
        torch.Size([5, 1])
    """
    for cls in type(loss).__mro__:  # the most derived loss class an algorithm names
        for learner in ALGORITHMS.values():
            if learner.torchrl_loss is cls:
                return learner.value_from_loss(loss, live=live)
    known = ", ".join(c.torchrl_loss.__name__ for c in ALGORITHMS.values() if c.torchrl_loss)
    raise TypeError(
        f"value_from_loss supports {known}, got {type(loss).__name__}; build the value module "
        "yourself with QMaxValue / ActorCriticValue and with_params"
    )
