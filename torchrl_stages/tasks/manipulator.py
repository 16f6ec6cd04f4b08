"""Manipulator report: final-distance percentiles, effector trajectories, fine-stage value map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_stages.envs.manipulator import forward_kinematics, inverse_kinematics
from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask

EPISODES = 1000


def final_distances(
    rollout: TensorDict, length: torch.Tensor, scales: Sequence[float]
) -> torch.Tensor:
    """Effector-target distance at the end of each row's first episode, from its observations."""
    last = (length - 1).clamp(min=0)
    index = last.view(-1, 1, 1)
    obs = rollout["next", "observation"].gather(1, index.expand(-1, 1, 6)).squeeze(1)
    stage = rollout["next", "stage"].gather(1, index).squeeze(-1).squeeze(-1)
    scale = torch.as_tensor(scales, dtype=obs.dtype)[stage]
    return obs[:, 4:6].norm(dim=-1) * scale


@torch.no_grad()
def fine_value_map(
    task: StagedTask, learner: Learner, target: Sequence[float], half_width: float, n: int = 61
) -> np.ndarray:
    """The fine stage's ``V(s)`` on an ``n x n`` grid of effector positions around ``target``."""
    env = task.base_env(1)
    xs = torch.linspace(-half_width, half_width, n)
    gx, gy = torch.meshgrid(xs + target[0], xs + target[1], indexing="xy")
    points = torch.stack([gx, gy], -1).reshape(-1, 2)
    theta = inverse_kinematics(points, torch.ones(len(points), dtype=torch.bool))
    elbow, effector = forward_kinematics(theta)
    diff = (torch.as_tensor(target, dtype=points.dtype) - effector) / env.scales[1]
    obs = torch.cat([elbow, effector, diff], -1).float()
    td = TensorDict(
        observation=obs, stage=torch.ones(len(obs), 1, dtype=torch.long), batch_size=[len(obs)]
    )
    return learner.value()(td)["state_value"].reshape(n, n).numpy()


def report(
    task: StagedTask, learners: Sequence[Learner], run_dir: Path, plots: bool = True
) -> dict[str, Any]:
    """Manipulator metrics for ``eval.json`` (and the Fig. 4(b) panel when ``plots``)."""
    policy = StackedPolicy([learner.policy for learner in learners])
    env = task.task_env(EPISODES)
    env.set_seed(12345)
    stats, rollout = evaluate_policy(env, policy, env.base_env.max_steps)
    scales = list(env.base_env.scales)
    dist = final_distances(rollout, stats.length, scales)
    q = torch.tensor([0.5, 0.9, 0.99])
    out: dict[str, Any] = {
        "episodes": EPISODES,
        "success_rate": stats.success.float().mean().item(),
        "mean_steps_success": stats.summary()["mean_steps_success"],
        "final_distance_p50_p90_p99": torch.quantile(dist, q).tolist(),
    }
    if plots and not env.base_env.random_target and len(learners) == 2:
        from torchrl_stages.plots import plot_arm_figure

        target = [float(v) for v in env.base_env.targets.reshape(-1, 2)[0]]
        n = int(stats.length[:8].max())
        paths = rollout["next", "observation"][:8, :n, 2:4]
        starts = rollout["observation"][:8, 0, 2:4]
        effector_paths = [
            torch.cat([starts[i : i + 1], paths[i, : int(stats.length[i])]]).tolist()
            for i in range(len(starts))
        ]
        half = 2.0 * float(env.base_env.switch_distance)
        values = fine_value_map(task, learners[1], target, half)
        plot_arm_figure(
            effector_paths,
            values,
            target=target,
            half_width=half,
            switch_distance=float(env.base_env.switch_distance),
            out=run_dir / "manipulator.png",
        )
    return out
