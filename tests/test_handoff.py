"""Handoff diagnostics: the states where whole-task episodes enter the next stage, the error of
that stage's value there, and how far they lie from the stage's training starts."""

from __future__ import annotations

import logging

import pytest
import torch
from helpers import hydra_config, two_stage_grid
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_stages.evaluate import discounted_return
from torchrl_stages.handoff import Handoffs, collect_handoffs, handoff_diagnostics
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.task import StagedTask


def rollout(stages: list[list[int]], rewards: list[list[float]]) -> TensorDict:
    stage = torch.tensor(stages)
    nxt = torch.cat([stage[:, 1:], stage[:, -1:]], -1)
    B, T = stage.shape
    obs = torch.arange(B * T, dtype=torch.float32).view(B, T, 1)
    return TensorDict(
        {
            "stage": stage.unsqueeze(-1),
            "observation": obs,
            "next": {
                "stage": nxt.unsqueeze(-1),
                "observation": obs + 0.5,
                "reward": torch.tensor(rewards).unsqueeze(-1),
            },
        },
        batch_size=[B, T],
    )


def test_handoff_returns_are_the_stage_discounted_returns_after_the_crossing():
    gammas = [0.9, 0.8, 0.5]
    td = rollout(
        [[0, 0, 1, 1, 2, 2], [0, 1, 2, 2, 2, 2], [0, 0, 0, 0, 0, 0]],
        [[0, 0, 0.5, 0, 0, 1], [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0]],
    )
    length = torch.tensor([6, 4, 6])
    h01, h12 = collect_handoffs(td, length, gammas)
    # row 0 enters stage 1 at s_2 (the "next" of step 1); row 1 at s_1; row 2 never
    assert h01.states["observation"].squeeze(-1).tolist() == [1.5, 6.5]
    assert h12.states["observation"].squeeze(-1).tolist() == [3.5, 7.5]
    # the same as discounted_return over the rollout that starts at s'
    expected0 = discounted_return(td[0:1, 2:], torch.tensor([4]), gammas).item()
    expected1 = discounted_return(td[1:2, 1:], torch.tensor([3]), gammas).item()
    assert h01.returns.tolist() == pytest.approx([expected0, expected1])
    assert h01.returns.tolist() == pytest.approx([0.5 + 0.8 * 0.8 * 0.5 * 1.0, 0.8 * 0.5])
    assert h12.returns.tolist() == pytest.approx([0.5, 0.5])  # one step of stage 2, then r = 1
    both = Handoffs.cat([h01, Handoffs(None, torch.zeros(0, dtype=torch.float64))])
    assert len(both.returns) == 2 and both.states.shape == (2,)


class ConstantValue:
    """A learner stand-in whose value is ``value`` everywhere."""

    def __init__(self, value: float) -> None:
        self._value = value

    def value(self) -> TensorDictModule:
        return TensorDictModule(
            lambda obs: torch.full((*obs.shape[:-1], 1), self._value),
            in_keys=["observation"],
            out_keys=["state_value"],
        )


def grid(**env) -> StagedTask:
    return two_stage_grid({"gamma": 0.9, "num_envs": 16}, **env)


def handed_over(task: StagedTask, rows: list[int]) -> Handoffs:
    cells = torch.tensor([[r, 5] for r in rows])  # the first column of stage 1
    obs = task.spec_env.observation_of(cells)
    states = TensorDict({"observation": obs}, batch_size=[len(rows)])
    return Handoffs(states, torch.full((len(rows),), 0.5, dtype=torch.float64))


def test_states_outside_the_training_starts_are_reported():
    rows = list(range(10))  # stage 0 hands over on every row
    covered = grid()
    (record,) = handoff_diagnostics(
        covered, [None, ConstantValue(0.6)], [handed_over(covered, rows)], 0
    )
    assert record["episodes"] == 10 and record["boundary"] == "a -> b"
    assert record["value_error_mean"] == pytest.approx(0.1)
    assert record["value_bias"] == pytest.approx(0.1)
    assert record["outside_starts"] == 0.0 and not record["extrapolated"]
    # stage 1 starts only in rows 6-9: the handoffs on rows 0-5 are outside them
    missed = grid(stage_start_rows=[6, 10])
    (record,) = handoff_diagnostics(
        missed, [None, ConstantValue(0.6)], [handed_over(missed, rows)], 0
    )
    assert record["outside_starts"] == pytest.approx(0.6) and record["extrapolated"]
    assert record["start_distance_median"] > 0


def test_a_boundary_nobody_crossed_has_no_numbers():
    task = grid()
    empty = Handoffs(None, torch.zeros(0, dtype=torch.float64))
    (record,) = handoff_diagnostics(task, [None, ConstantValue(0.0)], [empty], 0)
    assert record == {"boundary": "a -> b", "stage": 0, "episodes": 0}


@pytest.mark.slow
def test_a_run_reports_its_handoffs_and_warns_where_the_value_is_extrapolated(tmp_path, caplog):
    """Two 10 x 10 grid worlds that learn in seconds: stage 1 trained from every row, and from
    rows 6-9 only while stage 0's episodes (from column 0, every row) hand over on any row."""
    base = [
        "task.env.size=10",
        "task.env.num_stages=2",
        "~task.stages.s2",
        "~task.stages.s3",
        "~task.stages.s4",
        "progress=false",
    ]
    with hydra_config(*base) as compose:
        [covered] = Experiment(compose(), tmp_path / "covered").run()
        with caplog.at_level(logging.WARNING):
            [missed] = Experiment(
                compose("+task.env.stage_start_rows=[6,10]"), tmp_path / "missed"
            ).run()
    (ok,), (bad,) = covered["handoff"], missed["handoff"]
    assert covered["success_rate"] == 1.0 and ok["episodes"] == 10
    assert ok["outside_starts"] == 0.0 and not ok["extrapolated"]
    assert bad["outside_starts"] > 0.25 and bad["extrapolated"]
    assert "handoff s0 -> s1" in caplog.text and "outside stage 1's training starts" in caplog.text
    assert (tmp_path / "covered" / "handoff.png").is_file()
