"""Tests for the multi-stage grid world and its dynamic-programming solution."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

import torchrl_stages.envs.gridworld.env
from torchrl_stages.envs import (
    GridWorldEnv,
    greedy_path_from_values,
    gridworld_optimal_values,
    measure_throughput,
)

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def step_cells(cells, actions, **kwargs):
    """One step from each cell with the matching action; returns (next cells, next td)."""
    cells = torch.as_tensor(cells)
    env = GridWorldEnv((len(cells),), start_cell=cells, **kwargs)
    td = env.reset()
    td["action"] = torch.as_tensor(actions, dtype=torch.int64).expand(len(cells))
    nxt = env.step(td)["next"]
    return env.cells_of(nxt["observation"]), nxt


# ------------------------------------------------------------------ dynamics
def test_moves_from_interior_cell():
    cells, nxt = step_cells([[12, 12]] * 4, [UP, DOWN, LEFT, RIGHT])
    assert cells.tolist() == [[11, 12], [13, 12], [12, 11], [12, 13]]
    assert (nxt["reward"] == 0).all() and not nxt["done"].any()


@pytest.mark.parametrize(
    ("action", "edge"),
    [
        (UP, lambda i: (0, i)),
        (DOWN, lambda i: (24, i)),
        (LEFT, lambda i: (i, 0)),
        (RIGHT, lambda i: (i, 24)),
    ],
)
def test_blocked_at_grid_edges(action, edge):
    start = [edge(i) for i in range(25) if edge(i) not in [(23, 24), (24, 23)]]
    cells, _ = step_cells(start, action)
    assert cells.tolist() == [list(c) for c in start]


def test_stage_boundaries_block_leftward_moves_only():
    starts = [[3, 5], [3, 6], [0, 10], [7, 15], [24, 20], [4, 19], [9, 4]]
    cells, _ = step_cells(starts, LEFT)
    assert cells.tolist() == [[3, 5], [3, 5], [0, 10], [7, 15], [24, 20], [4, 18], [9, 3]]
    cells, _ = step_cells([[3, 4], [3, 9], [3, 19]], RIGHT)  # moving right into a later strip
    assert cells.tolist() == [[3, 5], [3, 10], [3, 20]]


def test_reward_and_termination_on_entering_target():
    cells, nxt = step_cells([[23, 24], [24, 23], [22, 24], [24, 22]], [DOWN, RIGHT, DOWN, RIGHT])
    assert cells.tolist() == [[24, 24], [24, 24], [23, 24], [24, 23]]
    assert nxt["reward"].squeeze(-1).tolist() == [1.0, 1.0, 0.0, 0.0]
    assert nxt["reward"].dtype == torch.float32 and nxt["reward"].shape == (4, 1)
    assert nxt["terminated"].squeeze(-1).tolist() == [True, True, False, False]
    assert not nxt["truncated"].any()
    assert torch.equal(nxt["done"], nxt["terminated"])


def test_truncation_at_max_steps():
    env = GridWorldEnv((2,), start_cell=[[0, 0], [5, 5]], max_steps=3)
    td = env.reset()
    for t in range(1, 4):
        td["action"] = torch.tensor([LEFT, UP])  # blocked / free moves, never the target
        td = env.step(td)
        nxt = td["next"]
        assert (nxt["truncated"] == (t == 3)).all()
        assert not nxt["terminated"].any()
        assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
        td = td["next"].clone()


def test_done_is_terminated_or_truncated_in_rollout():
    env = GridWorldEnv((64,), start_stage=4, max_steps=10)
    env.set_seed(1)
    data = env.rollout(30, break_when_any_done=False)
    nxt = data["next"]
    assert nxt["terminated"].any() and nxt["truncated"].any()
    assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
    assert torch.equal(nxt["reward"] == 1.0, nxt["terminated"])


# ------------------------------------------------------------------ observations and stages
def test_observation_encoding_and_stage_fn_all_columns():
    cols = torch.arange(25)
    start = torch.stack([(cols * 7) % 25, cols], -1)
    env = GridWorldEnv((25,), start_cell=start)
    td = env.reset()
    obs = td["observation"]
    assert obs.dtype == torch.float32 and obs.shape == (25, 2)
    torch.testing.assert_close(obs, start.float() / 5.0)
    assert torch.equal(env.cells_of(obs), start)
    stage = env.stage_fn(td)
    assert stage.dtype == torch.int64 and stage.shape == (25, 1)
    assert stage.squeeze(-1).tolist() == [c // 5 for c in range(25)]
    assert torch.equal(env.stage_fn(obs), stage)  # a raw observation tensor works too


def test_stage_fn_on_batch_time_tensordict():
    env = GridWorldEnv((8,))
    env.set_seed(0)
    data = env.rollout(12, break_when_any_done=False)
    assert data.shape == (8, 12)
    stage = env.stage_fn(data["next"])
    assert stage.shape == (8, 12, 1)
    expected = env.cells_of(data["next", "observation"])[..., 1:] // 5
    assert torch.equal(stage, expected)
    flat = data.reshape(-1)  # replay-buffer style [N] batch
    assert torch.equal(env.stage_fn(flat), env.stage_fn(data).reshape(-1, 1))


# ------------------------------------------------------------------ starts
@pytest.mark.parametrize("k", range(5))
def test_start_stage(k):
    env = GridWorldEnv((4096,), start_stage=k)
    env.set_seed(k)
    cells = env.cells_of(env.reset()["observation"])
    assert ((cells[:, 1] // 5) == k).all()
    assert not ((cells[:, 0] == 24) & (cells[:, 1] == 24)).any()
    assert len({tuple(c) for c in cells.tolist()}) == (124 if k == 4 else 125)


def test_start_stage_is_mutable_and_validated():
    env = GridWorldEnv((16,))
    env.start_stage = 3
    assert (env.cells_of(env.reset()["observation"])[:, 1] // 5 == 3).all()
    env.start_stage = None
    assert (env.cells_of(env.reset()["observation"])[:, 1] == 0).all()
    for bad in (-1, 5):
        with pytest.raises(ValueError, match="start_stage"):
            env.start_stage = bad
    with pytest.raises(ValueError, match="start_stage"):
        GridWorldEnv(start_stage=7)


def test_default_start_is_column_zero_random_row():
    env = GridWorldEnv((4096,))
    env.set_seed(0)
    cells = env.cells_of(env.reset()["observation"])
    assert (cells[:, 1] == 0).all()
    assert len(set(cells[:, 0].tolist())) == 25


def test_start_cell_pair_and_per_element():
    env = GridWorldEnv((2, 3), start_cell=(4, 7))
    assert (env.cells_of(env.reset()["observation"]) == torch.tensor([4, 7])).all()
    per = torch.arange(12).reshape(2, 3, 2)
    env = GridWorldEnv((2, 3), start_cell=per)
    assert torch.equal(env.cells_of(env.reset()["observation"]), per)
    assert torch.equal(env.start_cell, per)
    with pytest.raises(ValueError, match="start_cell"):
        GridWorldEnv((2, 3), start_cell=torch.zeros(3, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="start_cell"):
        GridWorldEnv(start_cell=(0, 25))


def test_invalid_grid_arguments():
    with pytest.raises(ValueError, match="size.*num_stages"):
        GridWorldEnv(size=24, num_stages=5)
    with pytest.raises(ValueError, match="target"):
        GridWorldEnv(size=10, num_stages=2, target=(24, 24))
    with pytest.raises(ValueError, match="gammas"):
        gridworld_optimal_values([0.99] * 4)


def test_small_grid_default_target_is_bottom_right():
    env = GridWorldEnv((3,), size=10, num_stages=2, start_cell=[[8, 9], [9, 8], [0, 0]])
    assert env.target == (9, 9) and env.stage_width == 5
    td = env.reset()
    td["action"] = torch.tensor([DOWN, RIGHT, RIGHT])
    nxt = env.step(td)["next"]
    assert nxt["terminated"].squeeze(-1).tolist() == [True, True, False]
    check_env_specs(env)
    values = gridworld_optimal_values([0.9, 0.9], size=10, num_stages=2)
    assert values[0, 0] == pytest.approx(0.9**17)
    assert len(greedy_path_from_values(values, (0, 0), num_stages=2)) == 19


# ------------------------------------------------------------------ resets, specs, seeding
def test_partial_reset_leaves_other_elements_untouched():
    env = GridWorldEnv((4,), max_steps=5)
    env.set_seed(0)
    td = env.reset()
    rows = env.cells_of(td["observation"])[:, 0]
    for _ in range(3):
        td["action"] = torch.full((4,), RIGHT)
        td = env.step(td)["next"].clone()
    mask = torch.tensor([True, False, True, False])
    before = td["observation"].clone()
    td["_reset"] = mask.unsqueeze(-1)
    td = env.reset(td)
    cells = env.cells_of(td["observation"])
    assert torch.equal(td["observation"][~mask], before[~mask])
    assert torch.equal(cells[~mask], torch.stack([rows[~mask], torch.full((2,), 3)], -1))
    assert (cells[mask, 1] == 0).all()
    for _ in range(2):  # the step counters of non-reset elements kept running
        td["action"] = torch.full((4,), UP)
        td = env.step(td)["next"].clone()
    assert td["truncated"].squeeze(-1).tolist() == [False, True, False, True]


def test_step_and_maybe_reset_resets_done_elements():
    env = GridWorldEnv((3,), start_cell=[[23, 24], [0, 0], [5, 5]])
    td = env.reset()
    td["action"] = torch.tensor([DOWN, RIGHT, RIGHT])
    data, td = env.step_and_maybe_reset(td)
    assert data["next", "terminated"].squeeze(-1).tolist() == [True, False, False]
    assert env.cells_of(td["observation"]).tolist() == [[23, 24], [0, 1], [5, 6]]
    assert not td["done"].any()


@pytest.mark.parametrize("batch_size", [(), (7,), (2, 3)])
def test_check_env_specs(batch_size):
    env = GridWorldEnv(batch_size)
    check_env_specs(env)
    env.start_stage = 2
    check_env_specs(env)
    assert env.action_spec.shape == batch_size and env.action_spec.space.n == 4


def test_seeding_reproducibility():
    env = GridWorldEnv((64,), start_stage=1)
    outs = []
    for _ in range(2):
        env.set_seed(0)
        first = env.reset()
        second = env.reset()  # the generator advances between resets
        outs.append(torch.stack([first["observation"], second["observation"]]))
        assert not torch.equal(first["observation"], second["observation"])
    assert torch.equal(outs[0], outs[1])
    env.set_seed(1)
    assert not torch.equal(env.reset()["observation"], outs[0][0])


def test_stage_fn_is_picklable_bound_method():
    import pickle

    env = GridWorldEnv((2,))
    fn = pickle.loads(pickle.dumps(env.stage_fn))
    td = TensorDict(observation=torch.tensor([[0.0, 4.8], [1.0, 0.8]]), batch_size=[2])
    assert fn(td).squeeze(-1).tolist() == [4, 0]


# ------------------------------------------------------------------ dynamic programming
def test_optimal_values_homogeneous_gamma():
    values = gridworld_optimal_values([0.99] * 5)
    assert values.shape == (25, 25) and values.dtype.name == "float64"
    assert values[0, 0] == pytest.approx(0.99**47, rel=1e-12)
    assert values[24, 24] == 0.0
    assert values[23, 24] == pytest.approx(1.0) and values[24, 23] == pytest.approx(1.0)
    path = greedy_path_from_values(values, (0, 0))
    assert len(path) == 49 and path[0] == (0, 0) and path[-1] == (24, 24)


def test_greedy_path_heterogeneous_gammas():
    gammas = [0.9, 0.9, 0.9, 0.99, 0.9]
    values = gridworld_optimal_values(gammas)
    path = greedy_path_from_values(values, (0, 0), gammas=gammas)
    assert len(path) - 1 == 48 and path[-1] == (24, 24)
    vertical = [a for a, b in zip(path, path[1:], strict=False) if a[0] != b[0]]
    assert len(vertical) == 24
    assert all(15 <= c <= 19 for _, c in vertical)


def test_greedy_path_replays_in_env():
    values = gridworld_optimal_values([0.99] * 5)
    path = greedy_path_from_values(values, (7, 0))
    env = GridWorldEnv(start_cell=(7, 0))
    td = env.reset()
    deltas = {(-1, 0): UP, (1, 0): DOWN, (0, -1): LEFT, (0, 1): RIGHT}
    for a, b in zip(path, path[1:], strict=False):
        td["action"] = torch.tensor(deltas[(b[0] - a[0], b[1] - a[1])])
        td = env.step(td)
        assert tuple(env.cells_of(td["next", "observation"]).tolist()) == b
        td = td["next"].clone()
    assert td["terminated"].item() and td["reward"].item() == 1.0


# ------------------------------------------------------------------ misc
def test_measure_throughput_is_frames_over_elapsed_time(monkeypatch):
    ticks = iter([100.0, 102.5])  # start, end: 2.5 s of (fake) wall clock

    class FakeTime:
        @staticmethod
        def perf_counter() -> float:
            return next(ticks)

    monkeypatch.setattr(torchrl_stages.envs.gridworld.env, "time", FakeTime)
    assert measure_throughput(64, steps=10) == pytest.approx(10 * 64 / 2.5)
    assert next(ticks, None) is None  # exactly two readings: before and after the timed steps
