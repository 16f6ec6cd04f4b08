"""Manipulator report: final-distance percentiles, effector trajectories, fine-stage value map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from torchrl_stages.evaluate import TaskEvaluation
from torchrl_stages.learners import Learner
from torchrl_stages.task import StagedTask

from .._common import episode_path
from .env import inverse_kinematics

EXAMPLES = 8  # effector paths drawn in manipulator.png


def final_distances(final: TensorDictBase, scales: Sequence[float]) -> torch.Tensor:
    """Effector-target distance where each episode ended, from its last observation."""
    obs, stage = final["observation"], final["stage"].reshape(-1)
    scale = torch.as_tensor(scales, dtype=obs.dtype, device=obs.device)[stage]
    return obs[:, 4:6].norm(dim=-1) * scale


@torch.no_grad()
def fine_value_map(
    task: StagedTask, learner: Learner, target: Sequence[float], half_width: float, n: int = 61
) -> np.ndarray:
    """The fine stage's ``V(s)`` on an ``n x n`` grid of effector positions around ``target``."""
    env = task.base_env(1)
    dev = env.device
    xs = torch.linspace(-half_width, half_width, n, device=dev)
    gx, gy = torch.meshgrid(xs + target[0], xs + target[1], indexing="xy")
    points = torch.stack([gx, gy], -1).reshape(-1, 2)
    theta = inverse_kinematics(points, torch.ones(len(points), dtype=torch.bool, device=dev))
    stage = torch.ones(len(points), dtype=torch.long, device=dev)
    obs = env.observation_of(theta, torch.as_tensor(target, device=dev).expand_as(points), stage)
    td = TensorDict(observation=obs, stage=stage.unsqueeze(-1), batch_size=[len(obs)])
    return learner.value()(td)["state_value"].reshape(n, n).cpu().numpy()


def report(
    task: StagedTask,
    learners: Sequence[Learner],
    evaluation: TaskEvaluation,
    run_dir: Path,
    plots: bool = True,
) -> dict[str, Any]:
    """The final distances' percentiles, and the Fig. 4(b) panel when ``plots``."""
    env = task.base_env(1)
    dist = final_distances(evaluation.final, list(env.scales))
    q = torch.tensor([0.5, 0.9, 0.99], device=dist.device)
    out: dict[str, Any] = {"final_distance_p50_p90_p99": torch.quantile(dist, q).tolist()}
    if plots and not env.random_target and len(learners) == 2:
        from .figures import plot_arm_figure

        effector_paths = [
            episode_path(evaluation.rollout, "observation", i, n)[:, 2:4].tolist()
            for i, n in enumerate(evaluation.stats.length[:EXAMPLES].tolist())
        ]
        half = 2.0 * float(env.switch_distance)
        target = list(env.target)
        values = fine_value_map(task, learners[1], target, half)
        plot_arm_figure(
            effector_paths,
            values,
            target=target,
            half_width=half,
            switch_distance=float(env.switch_distance),
            out=run_dir / "manipulator.png",
        )
    return out
