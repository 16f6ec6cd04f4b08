"""Grid-world report: the greedy path from (0, 0) and the merged value map against dynamic
programming, and the paper's Fig. 2 panels."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_stages.evaluate import TaskEvaluation, evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask

from .._common import episode_path
from .env import gridworld_optimal_values, gridworld_shortest_steps


def greedy_path(task: StagedTask, policy: StackedPolicy, start: Sequence[int]) -> list[list[int]]:
    """Cells visited by the greedy stacked policy from ``start`` until its episode ends."""
    env = task.task_env(1, start_cell=tuple(start), start_stage=None)
    stats, rollout = evaluate_policy(env, policy, env.base_env.max_steps)
    observations = episode_path(rollout, "observation", 0, int(stats.length[0]))
    return env.base_env.cells_of(observations).tolist()


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
    size = env.size
    steps = torch.arange(size, device=env.device)
    rows, cols = torch.meshgrid(steps, steps, indexing="ij")
    cells = torch.stack([rows, cols], -1).reshape(-1, 2)
    td = TensorDict(observation=env.observation_of(cells), batch_size=[size * size])
    values = torch.stack(
        [learner.value()(td.clone())["state_value"].squeeze(-1) for learner in learners]
    )  # [N, S]
    stage = env.stage_fn(td).reshape(1, -1)
    return values.gather(0, stage).reshape(size, size).cpu().numpy()


def _gammas(task: StagedTask) -> list[float]:
    return [float(task.stage_cfg(k).gamma) for k in range(task.num_stages)]


def path_from_origin(task: StagedTask, policy: StackedPolicy) -> dict[str, Any]:
    """The greedy path from ``(0, 0)``: its cells and steps against the fewest, whether its
    discounted return is the optimal value, and its vertical moves per stage."""
    env = task.base_env(1)
    size, width, n, target = env.size, env.stage_width, env.num_stages, env.target
    gammas = _gammas(task)
    path = greedy_path(task, policy, (0, 0))
    reached = tuple(path[-1]) == tuple(target)
    optimal = gridworld_optimal_values(gammas, size=size, num_stages=n, target=target)
    # the discounted return of the path: gamma of the stage of every state left on the way
    stage_of = [min(c // width, n - 1) for _, c in path[:-1]]
    path_return = float(np.prod([gammas[k] for k in stage_of[:-1]])) if reached else 0.0
    best = float(optimal[0, 0])
    return {
        "path_from_origin": path,
        "path_from_origin_steps": len(path) - 1 if reached else None,
        "path_from_origin_optimal": bool(reached and abs(path_return - best) <= 1e-9 * best),
        "optimal_steps_from_origin": gridworld_shortest_steps(
            (0, 0), size=size, num_stages=n, target=target
        ),
        "vertical_moves_per_stage": vertical_moves_per_stage(path, width, n),
    }


def value_map_errors(task: StagedTask, learners: Sequence[Learner]) -> tuple[np.ndarray, dict]:
    """The merged value map and its largest and mean error off the target (Proposition 1)."""
    env = task.base_env(1)
    values = merged_value_map(task, learners)
    optimal = gridworld_optimal_values(
        _gammas(task), size=env.size, num_stages=env.num_stages, target=env.target
    )
    free = np.ones_like(optimal, dtype=bool)
    free[env.target] = False
    error = np.abs(values - optimal)[free]
    return values, {
        "value_map_max_abs_error": float(error.max()),
        "value_map_mean_abs_error": float(error.mean()),
    }


def probe(task: StagedTask, learners: Sequence[Learner]) -> dict[str, float]:
    """Whether the greedy path from (0, 0) is optimal, and the value map's largest error."""
    policy = StackedPolicy([learner.policy for learner in learners])
    _, errors = value_map_errors(task, learners)
    return {
        "path_optimal": float(path_from_origin(task, policy)["path_from_origin_optimal"]),
        "value_error": errors["value_map_max_abs_error"],
    }


def report(
    task: StagedTask,
    learners: Sequence[Learner],
    evaluation: TaskEvaluation,
    run_dir: Path,
    plots: bool = True,
) -> dict[str, Any]:
    """The greedy path from (0, 0) and the value map's error (the Fig. 2 panels when
    ``plots``); the whole-task evaluation covers every column-0 start."""
    env = task.base_env(1)
    size, width, target = env.size, env.stage_width, env.target
    policy = StackedPolicy([learner.policy for learner in learners])
    metrics = path_from_origin(task, policy)
    values, errors = value_map_errors(task, learners)
    np.save(run_dir / "value_map.npy", values)
    if plots:
        from .figures import plot_grid_trajectories, plot_value_map

        starts = [(size // 2, 0), (size - 1, 0)]
        paths = [metrics["path_from_origin"]] + [greedy_path(task, policy, s) for s in starts]
        plot_grid_trajectories(
            paths,
            size=size,
            stage_width=width,
            target=target,
            out=run_dir / "trajectories.png",
            labels=[f"({r},{c})" for r, c in [(0, 0), *starts]],
            title=f"greedy stacked policy, gammas={_gammas(task)}",
        )
        plot_value_map(
            values,
            stage_width=width,
            target=target,
            out=run_dir / "value_map.png",
            title="merged value V(s) = V_stage(s)(s)",
        )
    return {**metrics, **errors}
