"""The value a trained stage hands to the one before it, from a torchrl loss module.

For a drop-in training loop built on torchrl's own losses: :func:`value_from_loss` turns stage
k+1's loss into the frozen ``V_{k+1}(s)`` module that
:class:`~torchrl_stages.transforms.StageTransform` (``next_value=``) or
:class:`~torchrl_stages.transforms.StageRewardTransform` adds to stage k's transition rewards.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import LossModule

from torchrl_stages.learners import ALGORITHMS

__all__ = ["value_from_loss"]


def value_from_loss(loss: LossModule, *, live: bool = False) -> TensorDictModuleBase:
    """``V(s)`` from the *target* networks of a torchrl loss, writing ``"state_value"``: what
    the algorithm whose :attr:`~torchrl_stages.learners.Learner.torchrl_loss` it is hands to the
    stage before it (:meth:`~torchrl_stages.learners.Learner.value_from_loss`; e.g.
    ``max_a Q_target(s, a)`` for ``DQNLoss``, the minimum of the twin target critics at
    ``mu_target(s)`` for ``TD3Loss``).

    The module holds a copy of the target parameters (``live=True``: it reads them in place
    and follows the target updater, as the joint schedule needs). The loss must have been
    built with target networks (``delay_value`` / ``delay_actor`` / ``delay_qvalue``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Categorical
        >>> from torchrl.modules import MLP, QValueActor
        >>> from torchrl.objectives import DQNLoss, SoftUpdate
        >>> qnet = QValueActor(MLP(in_features=2, out_features=3, num_cells=[16]),
        ...                    in_keys=["observation"], spec=Categorical(3))
        >>> loss = DQNLoss(qnet, action_space="categorical", delay_value=True)
        >>> updater = SoftUpdate(loss, tau=0.05)
        >>> value = value_from_loss(loss)
        >>> td = TensorDict(observation=torch.zeros(5, 2), batch_size=[5])
        >>> value(td)["state_value"].shape
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
