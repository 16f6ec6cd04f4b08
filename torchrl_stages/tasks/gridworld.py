"""Grid-world report: every column-0 start, the greedy path from (0, 0), the merged value map."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_stages.envs import gridworld_optimal_values
from torchrl_stages.evaluate import evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask


def greedy_path(task: StagedTask, policy: StackedPolicy, start: Sequence[int]) -> list[list[int]]:
    """Cells visited by the greedy stacked policy from ``start`` until its episode ends."""
    env = task.task_env(1, start_cell=tuple(start))
    stats, rollout = evaluate_policy(env, policy, env.base_env.max_steps)
    n = int(stats.length[0])
    cells = env.base_env.cells_of(rollout["observation"][0, :n])
    last = env.base_env.cells_of(rollout["next", "observation"][0, n - 1 : n])
    return torch.cat([cells, last]).tolist()


def vertical_moves_per_stage(
    path: Sequence[Sequence[int]], stage_width: int, num_stages: int
) -> list[int]:
    """How many row changes happen from a cell of each stage."""
    counts = [0] * num_stages
    for (r0, c0), (r1, _) in zip(path[:-1], path[1:], strict=True):
        if r1 != r0:
            counts[c0 // stage_width] += 1
    return counts


@torch.no_grad()
def merged_value_map(task: StagedTask, learners: Sequence[Learner]) -> np.ndarray:
    """``V(s) = V_{stage(s)}(s)`` on every cell, ``(size, size)``, row 0 at the top."""
    env = task.base_env(1)
    size, width = env.size, env.stage_width
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    obs = torch.stack([rows, cols], -1).reshape(-1, 2).float() / 5.0
    td = TensorDict(observation=obs, batch_size=[size * size])
    values = torch.stack(
        [learner.value()(td.clone())["state_value"].squeeze(-1) for learner in learners]
    )  # [N, S]
    stage = (cols.reshape(-1) // width).clamp(max=len(learners) - 1)
    return values.gather(0, stage.unsqueeze(0)).squeeze(0).reshape(size, size).numpy()


def report(
    task: StagedTask, learners: Sequence[Learner], run_dir: Path, plots: bool = True
) -> dict[str, Any]:
    """Grid-world metrics for ``eval.json`` (and the Fig. 2 panels when ``plots``)."""
    env = task.base_env(1)
    size, width, n = env.size, env.stage_width, env.num_stages
    policy = StackedPolicy([learner.policy for learner in learners])
    starts = [[r, 0] for r in range(size)]
    col0 = task.task_env(size, start_cell=starts)
    stats, _ = evaluate_policy(col0, policy, env.max_steps)
    path = greedy_path(task, policy, (0, 0))
    reached = tuple(path[-1]) == tuple(env.target)
    gammas = [float(task.stage_cfg(k).gamma) for k in range(n)]
    values = merged_value_map(task, learners)
    optimal = gridworld_optimal_values(gammas, size=size, num_stages=n, target=env.target)
    free = np.ones_like(optimal, dtype=bool)
    free[env.target] = False  # the target is terminal: no value is learned there
    np.save(run_dir / "value_map.npy", values)
    if plots:
        from torchrl_stages.plots import plot_grid_trajectories, plot_value_map

        paths = [path] + [greedy_path(task, policy, s) for s in ([12, 0], [24, 0])]
        plot_grid_trajectories(
            paths,
            size=size,
            stage_width=width,
            target=env.target,
            out=run_dir / "trajectories.png",
            labels=["(0,0)", "(12,0)", "(24,0)"],
            title=f"greedy stacked policy, gammas={gammas}",
        )
        plot_value_map(
            values,
            stage_width=width,
            target=env.target,
            out=run_dir / "value_map.png",
            title="merged value V(s) = V_stage(s)(s)",
        )
    return {
        "column0_success_rate": stats.summary()["success_rate"],
        "column0_all_succeed": bool(stats.success.all()),
        "column0_mean_steps": stats.summary()["mean_steps"],
        "path_from_origin": path,
        "path_from_origin_steps": len(path) - 1 if reached else None,
        "optimal_steps_from_origin": (size - 1) * 2 if env.target == (size - 1, size - 1) else None,
        "vertical_moves_per_stage": vertical_moves_per_stage(path, width, n),
        "value_map_max_abs_error": float(np.abs(values - optimal)[free].max()),
        "value_map_mean_abs_error": float(np.abs(values - optimal)[free].mean()),
    }
