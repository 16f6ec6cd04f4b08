"""StackedPolicy: each batch element acts with the policy of its stage."""

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Categorical
from torchrl.envs import TransformedEnv
from torchrl.modules import QValueActor

from torchrl_stages.envs import GridWorldEnv
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.transforms import StageTransform

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def constant_policy(action: int, out_key="action") -> TensorDictModule:
    """Writes ``action`` (int64, one per batch element) whatever the observation."""
    return TensorDictModule(
        lambda obs: torch.full(obs.shape[:-1], action, dtype=torch.int64),
        ["observation"],
        [out_key],
    )


def td_with_stages(stages, obs_dim=2):
    stage = torch.as_tensor(stages, dtype=torch.int64).unsqueeze(-1)
    return TensorDict(
        observation=torch.randn(*stage.shape[:-1], obs_dim),
        stage=stage,
        batch_size=stage.shape[:-1],
    )


def test_routes_each_element_by_its_stage():
    policy = StackedPolicy([constant_policy(RIGHT), constant_policy(DOWN), constant_policy(UP)])
    assert policy.in_keys == ["stage", "observation"]
    assert policy.out_keys == ["action"]
    td = td_with_stages([0, 1, 2, 1, 0])
    obs = td["observation"].clone()
    out = policy(td)
    assert out is td
    assert out["action"].tolist() == [RIGHT, DOWN, UP, DOWN, RIGHT]
    assert out["action"].dtype == torch.int64
    assert torch.equal(out["observation"], obs)  # inputs untouched
    assert out["stage"].squeeze(-1).tolist() == [0, 1, 2, 1, 0]


def test_routes_observation_dependent_policies():
    p0 = TensorDictModule(lambda obs: obs * 10, ["observation"], ["out"])
    p1 = TensorDictModule(lambda obs: -obs, ["observation"], ["out"])
    td = td_with_stages([1, 0, 1])
    obs = td["observation"].clone()
    out = StackedPolicy([p0, p1])(td)["out"]
    assert torch.equal(out, torch.stack([-obs[0], obs[1] * 10, -obs[2]]))


@pytest.mark.parametrize("stages", [[0, 0, 0], [2, 2], [0, 2, 0, 2]])
def test_batch_where_a_stage_is_absent(stages):
    policy = StackedPolicy([constant_policy(RIGHT), constant_policy(DOWN), constant_policy(UP)])
    out = policy(td_with_stages(stages))
    expected = {0: RIGHT, 1: DOWN, 2: UP}
    assert out["action"].tolist() == [expected[s] for s in stages]


def counting_policy(action: int, calls: list) -> TensorDictModule:
    def act(obs):
        calls.append(obs.shape)
        return torch.full(obs.shape[:-1], action, dtype=torch.int64)

    return TensorDictModule(act, ["observation"], ["action"])


def test_a_stage_absent_from_the_batch_runs_only_in_the_first_call():
    """The first call runs every stage (it learns each output's shape); later calls leave out
    the stages absent from the batch."""
    calls0, calls1 = [], []
    policy = StackedPolicy([counting_policy(RIGHT, calls0), counting_policy(DOWN, calls1)])
    for stages in ([0, 0], [0, 0, 0], [1]):
        out = policy(td_with_stages(stages))
    assert calls0 == [torch.Size([2, 2]), torch.Size([3, 2])]
    assert calls1 == [torch.Size([2, 2]), torch.Size([1, 2])]
    assert out["action"].tolist() == [DOWN]


def test_skip_absent_false_runs_every_stage_policy_on_the_whole_batch():
    calls0, calls1 = [], []
    policy = StackedPolicy(
        [counting_policy(RIGHT, calls0), counting_policy(DOWN, calls1)], skip_absent=False
    )
    for _ in range(2):
        out = policy(td_with_stages([0, 0]))
    assert calls1 == [torch.Size([2, 2])] * 2 == calls0
    assert out["action"].tolist() == [RIGHT, RIGHT]


@pytest.mark.parametrize("out_key", ["per_stage", "shared"])
def test_skipping_absent_stages_changes_no_output(out_key):
    """The same outputs as when every stage runs: an output written by absent stages only is
    zeros, in its shape and dtype."""
    torch.manual_seed(1)
    policies = [
        TensorDictModule(
            nn.Linear(2, 3), ["observation"], [("out", str(k)) if out_key == "per_stage" else "out"]
        )
        for k in range(3)
    ]
    skipping, every = StackedPolicy(policies), StackedPolicy(policies, skip_absent=False)
    for stages in ([0, 1, 2], [2, 2, 2, 2], [[0, 0], [0, 0]], [1]):
        td = td_with_stages(stages)
        out, expected = skipping(td.clone()), every(td.clone())
        assert set(out.keys(True, True)) == set(expected.keys(True, True))
        for key in expected.keys(True, True):
            assert torch.equal(out[key], expected[key]), (stages, key)


def test_batch_and_time_dims():
    policy = StackedPolicy([constant_policy(RIGHT), constant_policy(DOWN)])
    stages = [[0, 0, 1, 1], [1, 1, 1, 1], [0, 1, 0, 1]]
    out = policy(td_with_stages(stages))
    assert out["action"].shape == (3, 4)
    expected = [[RIGHT if s == 0 else DOWN for s in row] for row in stages]
    assert out["action"].tolist() == expected


def test_multi_dim_outputs_are_masked_per_element():
    p0 = TensorDictModule(lambda obs: torch.ones(*obs.shape[:-1], 3), ["observation"], ["out"])
    p1 = TensorDictModule(
        lambda obs: torch.full((*obs.shape[:-1], 3), 2.0), ["observation"], ["out"]
    )
    out = StackedPolicy([p0, p1])(td_with_stages([[0, 1], [1, 0]]))["out"]
    assert out.shape == (2, 2, 3)
    assert out[..., 0].tolist() == [[1.0, 2.0], [2.0, 1.0]]
    assert torch.equal(out[..., 0:1].expand_as(out), out)


def per_stage_key_policies():
    """Stage 0 writes a continuous ("slider", "action"), stage 1 a discrete ("propelled",
    "action"), as in a task whose stages have different action spaces."""
    p0 = TensorDictModule(
        lambda obs: obs[..., :2] * 0 + torch.tensor([0.5, -0.5]),
        ["observation"],
        [("slider", "action")],
    )
    p1 = TensorDictModule(
        lambda obs: torch.full(obs.shape[:-1], 3, dtype=torch.int64),
        ["observation"],
        [("propelled", "action")],
    )
    return StackedPolicy([p0, p1])


def test_per_stage_action_keys_are_zero_elsewhere():
    policy = per_stage_key_policies()
    assert policy.out_keys == [("slider", "action"), ("propelled", "action")]
    out = policy(td_with_stages([0, 1, 1, 0]))
    slider, propelled = out["slider", "action"], out["propelled", "action"]
    assert slider.shape == (4, 2) and slider.dtype == torch.float32
    assert propelled.shape == (4,) and propelled.dtype == torch.int64
    assert slider.tolist() == [[0.5, -0.5], [0.0, 0.0], [0.0, 0.0], [0.5, -0.5]]
    assert propelled.tolist() == [0, 3, 3, 0]


def test_per_stage_action_keys_present_when_a_stage_is_absent():
    policy = per_stage_key_policies()
    out = policy(td_with_stages([0, 0, 0]))
    assert set(policy.out_keys) <= set(out.keys(True, True))
    assert out["propelled", "action"].tolist() == [0, 0, 0]


def test_stacked_policy_drives_a_grid_world_rollout():
    # stage 0 goes right, stage 1 goes down: from (0, 3) the path is (0,4) (0,5) (1,5) (2,5)
    base = GridWorldEnv((2,), size=10, num_stages=2, start_cell=[(0, 3), (7, 7)])
    env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
    policy = StackedPolicy([constant_policy(RIGHT), constant_policy(DOWN)])
    td = env.rollout(4, policy)
    cells = base.cells_of(td["next", "observation"])
    assert cells[0].tolist() == [[0, 4], [0, 5], [1, 5], [2, 5]]
    # the second row starts in stage 1 and goes down until the bottom edge blocks it
    assert cells[1].tolist() == [[8, 7], [9, 7], [9, 7], [9, 7]]
    assert td["action"][0].tolist() == [RIGHT, RIGHT, DOWN, DOWN]
    assert td["action"][1].tolist() == [DOWN] * 4


def test_stacked_q_actors():
    def qactor(best):
        lin = nn.Linear(2, 4)
        with torch.no_grad():
            lin.weight.zero_()
            lin.bias.copy_(torch.nn.functional.one_hot(torch.tensor(best), 4).float())
        return QValueActor(lin, in_keys=["observation"], spec=Categorical(4))

    policy = StackedPolicy([qactor(RIGHT), qactor(DOWN)])
    out = policy(td_with_stages([1, 0, 1]))
    assert out["action"].tolist() == [DOWN, RIGHT, DOWN]
    assert out["chosen_action_value"].squeeze(-1).tolist() == [1.0, 1.0, 1.0]
    assert out["action_value"].shape == (3, 4)
