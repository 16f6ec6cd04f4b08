"""Episode statistics of greedy rollouts and the whole-task evaluation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_stages import evaluate as evaluate_module
from torchrl_stages.evaluate import EpisodeStats, discounted_return, episode_stats, evaluate_task
from torchrl_stages.learners.dqn import DQNConfig
from torchrl_stages.runs.evaluation import format_summary
from torchrl_stages.task import StagedTask

T = 5


def _rollout(rows: list[dict[str, list]]) -> TensorDict:
    """A ``[B, T]`` rollout from per-row flags and rewards: each row gives ``terminated`` and
    ``truncated`` steps (``done`` is their union) and ``reward`` (``T`` floats)."""

    def flags(name: str) -> torch.Tensor:
        out = torch.zeros(len(rows), T, 1, dtype=torch.bool)
        for b, row in enumerate(rows):
            for t in row.get(name, []):
                out[b, t] = True
        return out

    terminated, truncated = flags("terminated"), flags("truncated")
    reward = torch.tensor([row["reward"] for row in rows], dtype=torch.float32).unsqueeze(-1)
    nxt = TensorDict(
        done=terminated | truncated,
        terminated=terminated,
        truncated=truncated,
        reward=reward,
        batch_size=[len(rows), T],
    )
    return TensorDict(next=nxt, batch_size=[len(rows), T])


ROWS = [
    # terminated at t=2; the reward after the end belongs to the next episode
    {"terminated": [2], "reward": [0.0, 0.5, 1.0, 7.0, 7.0]},
    # truncated at t=3: the time limit is not a success
    {"truncated": [3], "reward": [0.1, 0.1, 0.1, 0.1, 9.0]},
    # terminated and truncated on the same step: the task was done, a success
    {"terminated": [1], "truncated": [1], "reward": [0.0, 1.0, 5.0, 5.0, 5.0]},
    # first episode truncated at t=1, the second one terminates at t=3: only the first counts
    {"truncated": [1], "terminated": [3], "reward": [0.2, 0.3, 0.0, 1.0, 0.0]},
    # never done: the whole rollout, no success
    {"reward": [1.0, 2.0, 3.0, 4.0, 5.0]},
]


def test_episode_stats_reads_each_rows_first_episode():
    stats = episode_stats(_rollout(ROWS))
    assert stats.success.tolist() == [True, False, True, False, False]
    assert stats.length.tolist() == [3, 4, 2, 2, T]
    assert stats.ret.tolist() == pytest.approx([1.5, 0.4, 1.0, 0.5, 15.0])


def test_discounted_return_ignores_rewards_after_the_first_episode():
    rollout = _rollout(ROWS)
    stats = episode_stats(rollout)
    gamma = 0.5
    expected = [
        0.5 * 0.5 + 1.0 * 0.25,
        0.1 * (1 + 0.5 + 0.25 + 0.125),
        1.0 * 0.5,
        0.2 + 0.3 * 0.5,
        1.0 + 2.0 * 0.5 + 3.0 * 0.25 + 4.0 * 0.125 + 5.0 * 0.0625,
    ]
    assert discounted_return(rollout, stats.length, gamma).tolist() == pytest.approx(expected)


def test_discounted_return_uses_the_given_lengths():
    rollout = _rollout([{"reward": [1.0, 1.0, 1.0, 1.0, 1.0]}] * 3)
    out = discounted_return(rollout, torch.tensor([1, 3, 5]), 0.9)
    assert out.tolist() == pytest.approx([1.0, 1 + 0.9 + 0.81, sum(0.9**t for t in range(5))])


def test_summary_without_successes_has_no_success_steps():
    stats = EpisodeStats(
        success=torch.tensor([False, False]),
        length=torch.tensor([4, 6]),
        ret=torch.tensor([0.0, 1.0]),
    )
    summary = stats.summary()
    assert summary["success_rate"] == 0.0
    assert summary["mean_steps"] == pytest.approx(5.0)
    assert summary["mean_return"] == pytest.approx(0.5)
    assert summary["mean_steps_success"] is None
    assert summary["median_steps_success"] is None


def test_summary_counts_steps_of_successes_only():
    stats = EpisodeStats(
        success=torch.tensor([True, False, True, True]),
        length=torch.tensor([2, 100, 9, 4]),
        ret=torch.tensor([1.0, 0.0, 1.0, 1.0]),
    )
    summary = stats.summary()
    assert summary["success_rate"] == pytest.approx(0.75)
    assert summary["mean_steps"] == pytest.approx(115 / 4)
    assert summary["mean_return"] == pytest.approx(0.75)
    assert summary["mean_steps_success"] == pytest.approx(5.0)
    assert summary["median_steps_success"] == pytest.approx(4.0)


def test_episode_stats_cat_concatenates_rows():
    a = episode_stats(_rollout(ROWS[:2]))
    b = episode_stats(_rollout(ROWS[2:]))
    both = EpisodeStats.cat([a, b])
    whole = episode_stats(_rollout(ROWS))
    for field in ("success", "length", "ret"):
        assert torch.equal(getattr(both, field), getattr(whole, field))


# ------------------------------------------------------------------ whole-task evaluation
SIZE = 10


def _grid_task() -> StagedTask:
    return StagedTask(
        OmegaConf.create(
            {
                "name": "grid",
                "stages": {"a": {"gamma": 0.9}, "b": {"gamma": 0.9}},
                "env": {
                    "_target_": "torchrl_stages.envs.GridWorldEnv",
                    "size": SIZE,
                    "num_stages": 2,
                },
                "eval_env": {},
            }
        )
    )


def _right_then_down() -> TensorDictModule:
    """Moves right (3) until the last column, then down (1)."""

    def act(obs: torch.Tensor) -> torch.Tensor:
        col = torch.round(obs[..., 1] * 5).long()
        return torch.where(col < SIZE - 1, 3, 1)

    return TensorDictModule(act, ["observation"], ["action"])


def test_evaluate_task_with_a_scripted_policy():
    task = _grid_task()
    evaluation = evaluate_task(task, _right_then_down(), episodes=3, seed=0)
    rows = torch.arange(SIZE)
    assert evaluation.starts == "all"  # every column-0 start once, `episodes` ignored
    assert len(evaluation.stats.length) == SIZE
    assert evaluation.stats.success.all()
    assert evaluation.stats.length.tolist() == (18 - rows).tolist()
    assert evaluation.stats.ret.tolist() == [1.0] * SIZE
    # 5 steps from the cells of stage 0 (columns 0-4), the rest from stage 1
    expected = torch.stack([torch.full((SIZE,), 5), 13 - rows], -1)
    assert evaluation.steps_per_stage.tolist() == expected.tolist()
    # every episode ends on the target, in stage 1
    cells = torch.round(evaluation.final["observation"] * 5).long()
    assert cells.tolist() == [[SIZE - 1, SIZE - 1]] * SIZE
    assert evaluation.final["terminated"].all()
    assert evaluation.final["stage"].squeeze(-1).tolist() == [1] * SIZE
    assert evaluation.rollout.shape == (SIZE, 18)

    summary = evaluation.summary()
    assert summary["episodes"] == SIZE and summary["starts"] == "all"
    assert summary["success_rate"] == 1.0
    assert summary["mean_return"] == pytest.approx(1.0)
    assert summary["mean_steps"] == pytest.approx(13.5)
    assert summary["mean_steps_success"] == pytest.approx(13.5)
    assert summary["median_steps_success"] == pytest.approx(13.5)  # lengths 9..18
    assert summary["mean_steps_per_stage"] == pytest.approx([5.0, 8.5])
    assert sum(summary["mean_steps_per_stage"]) == pytest.approx(summary["mean_steps"])


@pytest.mark.parametrize(("start_cell", "starts"), [([0, 0], "fixed"), (None, "random")])
def test_whole_task_starts_are_called_random_only_where_they_differ(
    monkeypatch, start_cell, starts
):
    # an env that does not enumerate its starts: "fixed" when every episode started from the
    # same observation (a reset that draws nothing), "random" else
    task = _grid_task()
    task.cfg.env.start_cell = start_cell
    monkeypatch.setattr(task, "start_states", lambda stage: None)
    monkeypatch.setattr(evaluate_module, "CHUNK", 4)  # two chunks, each its own env
    evaluation = evaluate_task(task, _right_then_down(), episodes=6, seed=0)
    assert evaluation.summary()["starts"] == starts
    assert evaluation.summary()["episodes"] == 6
    if starts == "fixed":
        assert evaluation.stats.length.unique().tolist() == [18]
    shown = format_summary({"task": "grid", **evaluation.summary()}, Path("run"))
    wording = {"fixed": "(one fixed start)", "random": "(random starts)"}[starts]
    assert f"over 6 whole-task episodes {wording}" in shown


def test_evaluate_task_counts_failures_at_the_time_limit():
    task = _grid_task()
    stay = TensorDictModule(
        lambda obs: torch.zeros(obs.shape[:-1], dtype=torch.long), ["observation"], ["action"]
    )  # always "up": never reaches the target
    task.cfg.eval_env = {"max_steps": 7}
    evaluation = evaluate_task(task, stay, episodes=3, seed=0)
    assert not evaluation.stats.success.any()
    assert evaluation.stats.length.tolist() == [7] * SIZE
    assert evaluation.steps_per_stage.tolist() == [[7, 0]] * SIZE
    summary = evaluation.summary()
    assert summary["success_rate"] == 0.0 and summary["mean_steps_success"] is None


def _grid_task(size: int = 10) -> StagedTask:
    return StagedTask(
        OmegaConf.create(
            {
                "name": "grid",
                "stages": {"a": DQNConfig(gamma=0.9), "b": DQNConfig(gamma=0.9)},
                "env": {
                    "_target_": "torchrl_stages.envs.GridWorldEnv",
                    "size": size,
                    "num_stages": 2,
                    "max_steps": 40,
                },
            }
        )
    )


def _scripted_grid_policy() -> TensorDictModule:
    """Down to the last row, then right; up (blocked: stuck for good) from row 0. Episodes end
    after different numbers of steps, or never."""

    def act(observation: torch.Tensor) -> torch.Tensor:
        row = (observation[..., 0] * 5.0).round().long()
        down_or_right = torch.where(row < 9, 1, 3)
        return torch.where(row == 0, 0, down_or_right)

    return TensorDictModule(act, ["observation"], ["action"])


@pytest.mark.parametrize("stage", [None, 0, 1])
def test_rollouts_step_finished_grid_elements_on_with_the_same_first_episodes(stage, monkeypatch):
    """A grid world with fixed starts steps its finished elements on instead of resetting them:
    every first episode (length, success, return) is the one a rollout with resets gives."""
    from torchrl.envs import TransformedEnv

    from torchrl_stages.envs import GridWorldEnv
    from torchrl_stages.evaluate import can_step_finished, rollout_first_episodes

    task, policy = _grid_task(), _scripted_grid_policy()
    # stage 0's transition reward reads a stage-1 value: one that depends on the state
    value = TensorDictModule(lambda obs: obs[..., :1] * 0.1, ["observation"], ["state_value"])

    def make_env():
        if stage is None:
            return task.task_env()
        return task.stage_eval_env(stage, value if stage == 0 else None)

    def rollout():
        return rollout_first_episodes(make_env(), policy, 40)

    assert can_step_finished(make_env())
    with monkeypatch.context() as patch:
        patch.setattr(TransformedEnv, "step_and_maybe_reset", None)  # the path must not reset
        stepped_on = rollout()
    with monkeypatch.context() as patch:
        patch.setattr(GridWorldEnv, "can_step_finished", False)
        reference = rollout()
    a, b = episode_stats(stepped_on), episode_stats(reference)
    assert len(set(b.length.tolist())) > 2 and b.success.any() and not b.success.all()
    assert torch.equal(a.length, b.length) and torch.equal(a.success, b.success)
    assert torch.equal(a.ret, b.ret)
    assert torch.equal(
        discounted_return(stepped_on, a.length, 0.9), discounted_return(reference, b.length, 0.9)
    )


def test_only_fixed_grid_starts_let_a_rollout_step_finished_elements():
    """Random starts draw from the env's generator at every reset: skipping a reset would
    change what later resets draw, so those envs reset their finished elements. So do batched
    envs (which forward attribute lookups to their workers) and envs under any transform but
    ``StageTransform`` (a transform may keep state across steps or elements)."""
    from torchrl.envs import SerialEnv, StepCounter, TransformedEnv

    from torchrl_stages.envs import GridWorldEnv
    from torchrl_stages.evaluate import can_step_finished

    def grid(**kw):
        return GridWorldEnv((2,), size=10, num_stages=2, **kw)

    assert can_step_finished(grid(start_cell=(0, 0)))
    assert not can_step_finished(grid())
    assert not can_step_finished(grid(start_stage=1))
    assert not can_step_finished(grid(start_cell=(0, 0), start_stage=1))
    assert not can_step_finished(TransformedEnv(grid(start_cell=(0, 0)), StepCounter(5)))
    serial = SerialEnv(2, lambda: GridWorldEnv((1,), size=10, num_stages=2, start_cell=(0, 0)))
    assert not can_step_finished(serial)  # before and after its workers start
    serial.set_seed(0)
    assert not can_step_finished(serial)
    serial.close()
