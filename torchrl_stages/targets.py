"""The value a trained stage hands to the one before it, from a torchrl loss module.

For a drop-in training loop built on torchrl's own losses: :func:`target_value` turns stage
k+1's loss into the frozen ``V_{k+1}(s)`` module that
:class:`~torchrl_stages.transforms.StageTransform` (``next_value=``) or
:class:`~torchrl_stages.transforms.StageRewardTransform` adds to stage k's transition rewards.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import DDPGLoss, DQNLoss, LossModule, TD3Loss

from torchrl_stages.values import ActorCriticValue, QMaxValue, with_params

__all__ = ["target_value"]


def target_value(loss: LossModule, *, live: bool = False) -> TensorDictModuleBase:
    """``V(s)`` from the *target* networks of a torchrl loss, writing ``"state_value"``.

    * ``DQNLoss``: ``max_a Q_target(s, a)`` (:class:`~torchrl_stages.values.QMaxValue`);
    * ``DDPGLoss``: ``Q_target(s, mu_target(s))``;
    * ``TD3Loss``: the minimum of the twin target critics at ``mu_target(s)``
      (:class:`~torchrl_stages.values.ActorCriticValue`).

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
        >>> value = target_value(loss)
        >>> td = TensorDict(observation=torch.zeros(5, 2), batch_size=[5])
        >>> value(td)["state_value"].shape
        torch.Size([5, 1])
    """
    if isinstance(loss, TD3Loss):
        params = loss.target_qvalue_network_params
        critics = [
            with_params(loss.qvalue_network, params[i], live=live) for i in range(params.shape[0])
        ]
        actor = with_params(loss.actor_network, loss.target_actor_network_params, live=live)
        return ActorCriticValue(actor, critics)
    if isinstance(loss, DDPGLoss):
        actor = with_params(loss.actor_network, loss.target_actor_network_params, live=live)
        critic = with_params(loss.value_network, loss.target_value_network_params, live=live)
        return ActorCriticValue(actor, [critic])
    if isinstance(loss, DQNLoss):
        qnet = with_params(loss.value_network, loss.target_value_network_params, live=live)
        return QMaxValue(qnet)
    raise TypeError(
        f"target_value supports DQNLoss, DDPGLoss and TD3Loss, got {type(loss).__name__}; "
        "build the value module yourself with QMaxValue / ActorCriticValue and with_params"
    )
