"""Greedy rollouts and their episode statistics (stage-level and whole-task)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type


@torch.no_grad()
def rollout_first_episodes(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int
) -> TensorDictBase:
    """Greedy rollout ``[*batch, T]`` until every batch element has finished one episode.

    Elements that finish early are reset and keep stepping; :func:`episode_stats` reads only each
    element's first episode. ``T <= max_steps``.
    """
    steps = []
    finished = torch.zeros(env.batch_size, dtype=torch.bool, device=env.device)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        for _ in range(max_steps):
            td = policy(td)
            td, td_next = env.step_and_maybe_reset(td)
            steps.append(td)
            finished |= td.get(("next", "done")).reshape(env.batch_size)
            if finished.all():
                break
            td = td_next
    return torch.stack(steps, dim=-1)


@dataclass
class EpisodeStats:
    """Statistics of each batch element's first episode in a rollout."""

    success: torch.Tensor  # bool [B]: ended by termination (not truncation, not unfinished)
    length: torch.Tensor  # int64 [B]: steps of the first episode
    ret: torch.Tensor  # float [B]: undiscounted return of the first episode

    def summary(self) -> dict[str, float]:
        ok = self.success
        return {
            "success_rate": ok.float().mean().item(),
            "mean_return": self.ret.mean().item(),
            "mean_steps": self.length.float().mean().item(),
            "mean_steps_success": self.length[ok].float().mean().item()
            if ok.any()
            else float("nan"),
        }


def episode_stats(rollout: TensorDictBase) -> EpisodeStats:
    """Success, length and return of the first episode of each row of a ``[B, T]`` rollout."""
    done = rollout.get(("next", "done")).squeeze(-1)  # [B, T]
    terminated = rollout.get(("next", "terminated")).squeeze(-1)
    reward = rollout.get(("next", "reward")).squeeze(-1)
    T = done.shape[-1]
    steps = torch.arange(T, device=done.device)
    any_done = done.any(-1)
    first = torch.where(
        any_done, done.float().argmax(-1), torch.full_like(any_done, T - 1, dtype=torch.long)
    )
    in_first = steps <= first.unsqueeze(-1)
    success = any_done & terminated.gather(-1, first.unsqueeze(-1)).squeeze(-1)
    length = torch.where(any_done, first + 1, torch.full_like(first, T))
    return EpisodeStats(success=success, length=length, ret=(reward * in_first).sum(-1))


def discounted_return(rollout: TensorDictBase, length: torch.Tensor, gamma: float) -> torch.Tensor:
    """``sum_t gamma^t r_t`` over each row's first episode (``length``: its episode lengths)."""
    reward = rollout.get(("next", "reward")).squeeze(-1)  # [B, T]
    steps = torch.arange(reward.shape[-1], device=reward.device)
    weights = torch.where(steps < length.unsqueeze(-1), gamma**steps, 0.0)
    return (reward * weights).sum(-1)


def evaluate_policy(
    env: EnvBase, policy: TensorDictModuleBase, max_steps: int
) -> tuple[EpisodeStats, TensorDictBase]:
    """Greedy first-episode statistics of ``policy`` on ``env``, and the rollout itself."""
    rollout = rollout_first_episodes(env, policy, max_steps)
    return episode_stats(rollout), rollout
