"""MiniGrid report: the level, how many steps each stage took, and the figure of one episode."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from torchrl_stages.evaluate import TaskEvaluation, ended_well
from torchrl_stages.learners import Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.task import StagedTask

from .env import stage_names

TILE = 32  # pixels per cell in minigrid.png
FIGURE_SEED = 0  # the layout drawn in minigrid.png


@torch.no_grad()
def greedy_episode(task: StagedTask, learners: Sequence[Learner], seed: int):
    """One greedy whole-task episode on the layout of ``seed``: its cells, the stage of each,
    whether it succeeded and the level's picture at its start."""
    env = task.task_env(1, vectorize="sync")
    try:
        env.set_seed(seed)
        start = env.reset()
        level = env.base_env._env.envs[0].unwrapped
        frame = level.get_frame(highlight=False, tile_size=TILE)
        policy = StackedPolicy([learner.policy for learner in learners])
        steps = int(env.base_env.max_steps)
        rollout = env.rollout(steps, policy, auto_reset=False, tensordict=start).squeeze(0)
        size = max(level.width, level.height)
        features = torch.cat([rollout["observation"][:1], rollout["next", "observation"]])
        cells = (features[:, :2] * size).round().long().tolist()
        stages = torch.cat([rollout["stage"][:1], rollout["next", "stage"]]).squeeze(-1).tolist()
        success = bool(ended_well(rollout[-1:])[-1])
    finally:
        env.close()
    return cells, stages, success, frame


def report(
    task: StagedTask,
    learners: Sequence[Learner],
    evaluation: TaskEvaluation,
    run_dir: Path,
    plots: bool = True,
) -> dict[str, Any]:
    """The level and the stage names for ``eval.json``; ``minigrid.png`` (one greedy episode,
    its path colored by stage) when ``plots``."""
    env_id = str(task.cfg.env.env_id)
    names = stage_names(env_id)
    if plots:
        from .figures import plot_level

        cells, stages, success, frame = greedy_episode(task, learners, FIGURE_SEED)
        plot_level(
            frame,
            cells,
            stages,
            stage_names=names,
            tile=TILE,
            out=run_dir / "minigrid.png",
            title=f"{env_id}: {len(cells) - 1} steps, {'success' if success else 'failure'}",
        )
    return {"level": env_id, "stages": names}
