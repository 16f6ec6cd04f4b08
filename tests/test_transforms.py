"""StageTransform: stage tags, transition flags and stage k's view of a step.

Geometry used throughout: ``GridWorldEnv(size=10, num_stages=2)`` has two strips of width 5
(columns 0-4 are stage 0, 5-9 stage 1), target (9, 9), and observation ``[row, col] / 5``. The
value modules below are known functions of the observation, so that ``V(s_t)`` and ``V(s_{t+1})``
differ and every rewritten reward can be computed by hand.
"""

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Categorical, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, RewardSum, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from torchrl_stages.envs import GridWorldEnv
from torchrl_stages.evaluate import ended_well, episode_stats
from torchrl_stages.transforms import StageRewardTransform, StageTransform, freeze

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3
GAMMA = 0.9


def cell_sum_value(scale: float = 1.0) -> TensorDictModule:
    """``V(s) = scale * (row + col)`` of the grid-world cell encoded in ``observation``."""
    return TensorDictModule(
        lambda obs: obs.sum(-1, keepdim=True) * 5.0 * scale, ["observation"], ["state_value"]
    )


def const_value(value: float) -> TensorDictModule:
    return TensorDictModule(
        lambda obs: torch.full_like(obs[..., :1], value), ["observation"], ["state_value"]
    )


def linear_value(weight: tuple[float, float], bias: float = 0.0) -> TensorDictModule:
    lin = nn.Linear(2, 1)
    with torch.no_grad():
        lin.weight.copy_(torch.tensor([weight]))
        lin.bias.fill_(bias)
    return TensorDictModule(lin, ["observation"], ["state_value"])


def make_env(start_cells, *, env_kwargs=None, **transform_kwargs):
    """A batched grid world (one row per start cell) wrapped in a StageTransform."""
    env_kwargs = {"size": 10, "num_stages": 2, "start_cell": start_cells, **(env_kwargs or {})}
    base = GridWorldEnv((len(start_cells),), **env_kwargs)
    transform = StageTransform(base.stage_fn, base.num_stages, **transform_kwargs)
    return TransformedEnv(base, transform), base, transform


def step(env, actions, td=None):
    """One step with the given actions (from a fresh reset unless ``td`` is given)."""
    td = env.reset() if td is None else td
    td["action"] = torch.as_tensor(actions, dtype=torch.int64).expand(env.batch_size).clone()
    return env.step(td)


def col(x):
    """``[B, 1]`` tensor -> list of its entries."""
    return x.reshape(-1).tolist()


# ---------------------------------------------------------------------- specs and tags
@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_check_env_specs_tag_only(batch):
    base = GridWorldEnv(batch, size=10, num_stages=2, max_steps=12)
    env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
    check_env_specs(env, seed=0)


@pytest.mark.parametrize("batch", [(), (5,)])
def test_check_env_specs_training_mode(batch):
    base = GridWorldEnv(batch, size=10, num_stages=2, max_steps=12, start_stage=0)
    t = StageTransform(base.stage_fn, 2, train_stage=0, next_value=cell_sum_value(), gamma=GAMMA)
    env = TransformedEnv(base, t)
    check_env_specs(env, seed=0)
    # the last stage trains without a next value
    base1 = GridWorldEnv(batch, size=10, num_stages=2, max_steps=12, start_stage=1)
    check_env_specs(TransformedEnv(base1, StageTransform(base1.stage_fn, 2, train_stage=1)))


def test_stage_declared_in_observation_spec():
    base = GridWorldEnv((5,), size=10, num_stages=2)
    env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
    spec = env.observation_spec
    assert spec["stage"].dtype == torch.int64
    assert spec["stage"].shape == torch.Size([5, 1])
    assert spec["stage"].space.n == 2
    assert spec["stage_transition"].dtype == torch.bool
    assert spec["stage_transition"].shape == torch.Size([5, 1])
    assert "stage" in env.full_observation_spec_unbatched.keys()


def test_tags_on_reset_and_every_step():
    # rows start at columns 3, 4, 5 and move right once
    env, _, _ = make_env([(0, 3), (1, 4), (2, 5)])
    td = env.reset()
    assert td["stage"].dtype == torch.int64 and td["stage"].shape == (3, 1)
    assert col(td["stage"]) == [0, 0, 1]
    assert col(td["stage_transition"]) == [False, False, False]
    td = step(env, RIGHT, td)
    assert td["stage"].shape == td["next", "stage"].shape == (3, 1)
    assert col(td["stage"]) == [0, 0, 1]
    assert col(td["next", "stage"]) == [0, 1, 1]
    assert td["next", "stage_transition"].dtype == torch.bool
    assert col(td["next", "stage_transition"]) == [False, True, False]
    # untrained tag-only mode: nothing else changes
    assert col(td["next", "reward"]) == [0.0, 0.0, 0.0]
    assert col(td["next", "done"]) == [False, False, False]


def test_rollout_tags_follow_the_cells():
    env, base, _ = make_env([(0, 0), (4, 3)])
    td = env.rollout(7, policy=lambda td: td.set("action", torch.full((2,), RIGHT)))
    assert td["stage"].shape == td["next", "stage"].shape == (2, 7, 1)
    cells = base.cells_of(td["next", "observation"])
    assert torch.equal(td["next", "stage"].squeeze(-1), cells[..., 1] // 5)
    # the root tag at t+1 is the "next" tag at t
    assert torch.equal(td["stage"][:, 1:], td["next", "stage"][:, :-1])
    # one transition per row: column 4 -> 5 at step 4 (row 0) and step 1 (row 1)
    assert td["next", "stage_transition"].squeeze(-1).nonzero().tolist() == [[0, 4], [1, 1]]


def test_partial_reset_only_changes_reset_rows():
    env, base, _ = make_env([(0, 0)] * 4, env_kwargs={"start_cell": None, "start_stage": 0})
    td = env.reset()
    assert col(td["stage"]) == [0, 0, 0, 0]
    base.start_stage = 1  # new starts are inside stage 1
    td.set("_reset", torch.tensor([[True], [False], [True], [False]]))
    td = env.reset(td)
    assert col(td["stage"]) == [1, 0, 1, 0]
    assert col(td["stage_transition"]) == [False] * 4
    assert (base.cells_of(td["observation"])[:, 1] // 5).tolist() == [1, 0, 1, 0]


def test_partial_reset_keeps_tags_of_rows_that_are_not_reset():
    # A step moves row 1 into stage 1; then only row 0 is reset (back to its start).
    env, base, _ = make_env([(0, 3), (0, 4), (0, 2)])
    td = step(env, RIGHT)
    assert col(td["next", "stage"]) == [0, 1, 0]
    td = td["next"].clone()
    td.set("_reset", torch.tensor([[True], [False], [False]]))
    td = env.reset(td)
    assert col(td["stage"]) == [0, 1, 0]
    assert base.cells_of(td["observation"]).tolist() == [[0, 3], [0, 5], [0, 3]]


def test_collector_and_serial_env_carry_the_tag():
    def make():
        base = GridWorldEnv(size=10, num_stages=2, max_steps=8, start_cell=(2, 3))
        return TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))

    serial = SerialEnv(2, make)
    check_env_specs(serial, seed=0)
    policy = TensorDictModule(
        lambda obs: torch.full(obs.shape[:-1], RIGHT, dtype=torch.int64),
        ["observation"],
        ["action"],
    )
    collector = Collector(
        serial,
        policy,
        frames_per_batch=8,
        total_frames=8,
        auto_register_policy_transforms=False,
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.shape == (2, 4)
    assert batch["stage"].dtype == torch.int64 and batch["stage"].shape == (2, 4, 1)
    # (2, 3) -> (2, 4) -> (2, 5) -> ...: the transition is the second step of each env
    assert batch["stage"].squeeze(-1).tolist() == [[0, 0, 1, 1]] * 2
    assert batch["next", "stage"].squeeze(-1).tolist() == [[0, 1, 1, 1]] * 2
    assert (
        batch["next", "stage_transition"].squeeze(-1).tolist() == [[False, True, False, False]] * 2
    )


# ---------------------------------------------------------------------- monotonicity
def row_stage_fn(td):
    """A stage function that can decrease: stage 1 on rows >= 5 (the grid lets rows go back)."""
    obs = td if isinstance(td, torch.Tensor) else td.get("observation")
    return (torch.round(obs[..., :1] * 5) >= 5).long()


def test_stage_never_decreases():
    base = GridWorldEnv((2,), size=10, num_stages=2, start_cell=[(4, 0), (4, 1)])
    env = TransformedEnv(base, StageTransform(row_stage_fn, 2))
    td = env.reset()
    stages, transitions = [], []
    for action in [DOWN, UP, UP, DOWN, DOWN]:  # rows 5, 4, 3, 4, 5
        td = step(env, action, td)
        stages.append(col(td["next", "stage"]))
        transitions.append(col(td["next", "stage_transition"]))
        td = step_mdp(td)
    assert stages == [[1, 1]] * 5
    assert transitions == [[True, True]] + [[False, False]] * 4
    # Back on row 4 (stage_fn says 0, the tag stays 1), then only row 0 is reset: its tag is
    # recomputed from its start, row 1 keeps its monotone tag.
    td = step_mdp(step(env, UP, td))
    assert col(td["stage"]) == [1, 1]
    td.set("_reset", torch.tensor([[True], [False]]))
    td = env.reset(td)
    assert col(td["stage"]) == [0, 1]


def test_stage_never_decreases_in_training_mode():
    # Going back across the boundary is not a second transition: no second reward rewrite.
    base = GridWorldEnv((1,), size=10, num_stages=2, start_cell=(4, 0))
    env = TransformedEnv(base, StageTransform(row_stage_fn, 2, train_stage=1, gamma=GAMMA))
    td = env.reset()
    for action in [DOWN, UP, DOWN]:
        td = step(env, action, td)
        assert col(td["next", "stage"]) == [1]
        assert col(td["next", "terminated"]) == [False]
        td = step_mdp(td)


# ---------------------------------------------------------------------- composition
def test_compose_with_step_counter_and_reward_sum():
    base = GridWorldEnv((2,), size=10, num_stages=2, start_cell=[(3, 3), (0, 0)])
    t = StageTransform(base.stage_fn, 2, train_stage=0, next_value=cell_sum_value(), gamma=GAMMA)
    env = TransformedEnv(base, Compose(t, StepCounter(max_steps=4), RewardSum()))
    check_env_specs(env, seed=0)
    td = env.rollout(
        2,
        policy=lambda td: td.set("action", torch.full((2,), RIGHT)),
        break_when_any_done=False,
    )
    # row 0: (3,3) -> (3,4) -> (3,5): the second step enters stage 1 and ends stage 0's episode
    assert td["next", "reward"][0].reshape(-1).tolist() == pytest.approx([0.0, GAMMA * 8])
    assert td["next", "episode_reward"][0].reshape(-1).tolist() == pytest.approx([0.0, GAMMA * 8])
    assert col(td["next", "terminated"][0]) == [False, True]
    assert col(td["next", "step_count"][0]) == [1, 2]
    assert col(td["next", "episode_reward"][1]) == [0.0, 0.0]


def test_reward_sum_after_stage_transform_accumulates_rewritten_reward():
    base = GridWorldEnv((1,), size=10, num_stages=2, start_cell=(3, 2))
    t = StageTransform(base.stage_fn, 2, train_stage=0, next_value=const_value(2.0), gamma=0.5)
    env = TransformedEnv(base, Compose(t, RewardSum()))
    td = env.rollout(3, policy=lambda td: td.set("action", torch.full((1,), RIGHT)))
    assert td["next", "episode_reward"][0, -1].item() == pytest.approx(1.0)  # 0 + 0 + 0.5 * 2
    assert td["next", "done"][0, -1].item()


def test_stage_transform_after_another_transform():
    base = GridWorldEnv((3,), size=10, num_stages=2, start_cell=[(3, 4), (3, 3), (3, 0)])
    t = StageTransform(base.stage_fn, 2, train_stage=0, next_value=cell_sum_value(), gamma=GAMMA)
    env = TransformedEnv(base, Compose(StepCounter(max_steps=1), t))
    check_env_specs(env, seed=0)
    td = step(env, RIGHT)
    assert col(td["stage"]) == [0, 0, 0]
    assert col(td["next", "stage"]) == [1, 0, 0]
    # truncated by the StepCounter before it; the transition row is also terminal for stage 0
    assert col(td["next", "truncated"]) == [True, True, True]
    assert col(td["next", "terminated"]) == [True, False, False]
    assert col(td["next", "reward"]) == pytest.approx([GAMMA * 8, 0.0, 0.0])


# ---------------------------------------------------------------------- §1.3 targets by hand
def test_transition_reward_uses_next_state_value():
    """(a) r' = r + gamma * V(s_{t+1}); terminated and done are set."""
    env, _, _ = make_env([(3, 4), (6, 4)], train_stage=0, next_value=cell_sum_value(), gamma=GAMMA)
    td = step(env, RIGHT)
    nxt = td["next"]
    # s_{t+1} = (3, 5) and (6, 5): V = 8 and 11 (V(s_t) would be 7 and 10)
    assert col(nxt["reward"]) == pytest.approx([GAMMA * 8, GAMMA * 11])
    assert col(nxt["terminated"]) == [True, True]
    assert col(nxt["done"]) == [True, True]
    assert col(nxt["truncated"]) == [False, False]
    assert col(nxt["stage_transition"]) == [True, True]
    # the value module did not write into the env output
    assert "state_value" not in nxt.keys() and "state_value" not in td.keys()


def test_transition_reward_with_a_learned_value_module():
    env, _, _ = make_env(
        [(3, 4)], train_stage=0, next_value=linear_value((2.0, -1.0), 0.5), gamma=GAMMA
    )
    nxt = step(env, RIGHT)["next"]
    obs = torch.tensor([3.0, 5.0]) / 5
    expected = GAMMA * (2.0 * obs[0] - obs[1] + 0.5)
    assert nxt["reward"].item() == pytest.approx(expected.item(), abs=1e-6)


def test_no_transition_leaves_reward_and_flags():
    """(b) no transition: reward and terminated unchanged."""
    env, _, _ = make_env(
        [(3, 3), (3, 4), (8, 9)], train_stage=0, next_value=const_value(100.0), gamma=GAMMA
    )
    td = step(env, [RIGHT, UP, DOWN])
    nxt = td["next"]
    # row 0 stays in stage 0, row 1 too; row 2 is in stage 1 and enters the target
    assert col(nxt["stage_transition"]) == [False, False, False]
    assert col(nxt["reward"]) == [0.0, 0.0, 1.0]
    assert col(nxt["terminated"]) == [False, False, True]
    assert col(nxt["done"]) == [False, False, True]


def test_transition_that_terminates_the_task_gets_no_value_term():
    """(c) the transition step also enters the task's target: r' = r (no V term)."""
    # 5 strips of width 2; the target (0, 2) is the first cell of stage 1
    env, _, _ = make_env(
        [(0, 1), (1, 1)],
        env_kwargs={"size": 10, "num_stages": 5, "target": (0, 2)},
        train_stage=0,
        next_value=const_value(3.0),
        gamma=GAMMA,
    )
    nxt = step(env, RIGHT)["next"]
    assert col(nxt["stage_transition"]) == [True, True]
    assert col(nxt["reward"]) == pytest.approx([1.0, GAMMA * 3.0])
    assert col(nxt["terminated"]) == [True, True]
    assert col(nxt["done"]) == [True, True]


def test_truncation_without_transition_is_not_termination():
    """(d) time limit: terminated stays False (the learner bootstraps through it)."""
    env, _, _ = make_env(
        [(3, 3), (3, 4)],
        env_kwargs={"max_steps": 1},
        train_stage=0,
        next_value=cell_sum_value(),
        gamma=GAMMA,
    )
    nxt = step(env, RIGHT)["next"]
    # row 0: (3,3) -> (3,4), truncated only; row 1: (3,4) -> (3,5), truncated AND a transition
    assert col(nxt["truncated"]) == [True, True]
    assert col(nxt["done"]) == [True, True]
    assert col(nxt["terminated"]) == [False, True]
    assert col(nxt["reward"]) == pytest.approx([0.0, GAMMA * 8])


def test_truncation_with_step_counter_is_not_termination():
    base = GridWorldEnv((1,), size=10, num_stages=2, start_cell=(3, 0))
    t = StageTransform(base.stage_fn, 2, train_stage=0, next_value=const_value(5.0), gamma=GAMMA)
    env = TransformedEnv(base, Compose(t, StepCounter(max_steps=2)))
    td = env.rollout(2, policy=lambda td: td.set("action", torch.full((1,), RIGHT)))
    assert col(td["next", "truncated"]) == [False, True]
    assert col(td["next", "terminated"]) == [False, False]
    assert col(td["next", "reward"]) == [0.0, 0.0]


def test_transition_out_of_another_stage_is_not_rewritten():
    """(e) train_stage=k only rewrites the step that leaves stage k."""
    env, _, _ = make_env(
        [(3, 1), (3, 3), (3, 5)],
        env_kwargs={"size": 10, "num_stages": 5},  # strips of width 2
        train_stage=1,
        next_value=const_value(7.0),
        gamma=GAMMA,
    )
    nxt = step(env, RIGHT)["next"]
    # row 0 leaves stage 0 (not trained), row 1 leaves stage 1 (trained), row 2 leaves stage 2
    assert col(nxt["stage_transition"]) == [True, True, True]
    assert col(nxt["reward"]) == pytest.approx([0.0, GAMMA * 7.0, 0.0])
    assert col(nxt["terminated"]) == [False, True, False]
    assert col(nxt["done"]) == [False, True, False]


def test_stage_gamma_is_the_trained_stage_discount():
    for gamma in (0.5, 1.0):
        env, _, _ = make_env([(3, 4)], train_stage=0, next_value=const_value(4.0), gamma=gamma)
        assert step(env, RIGHT)["next", "reward"].item() == pytest.approx(gamma * 4.0)


def test_last_stage_has_ordinary_targets():
    """(f) the last stage has no next stage: nothing is rewritten."""
    env, _, t = make_env([(8, 9), (4, 7)], train_stage=1, gamma=GAMMA)
    assert t.next_value is None
    nxt = step(env, [DOWN, RIGHT])["next"]
    assert col(nxt["reward"]) == [1.0, 0.0]
    assert col(nxt["terminated"]) == [True, False]
    base = GridWorldEnv((1,), size=10, num_stages=2)
    with pytest.raises(ValueError, match="next_value"):
        StageTransform(base.stage_fn, 2, train_stage=1, next_value=const_value(1.0))
    with pytest.raises(ValueError, match="next_value"):
        StageTransform(base.stage_fn, 2, next_value=const_value(1.0))  # no train_stage


def test_train_stage_without_next_value_still_ends_the_stage_episode():
    env, _, _ = make_env([(3, 4)], train_stage=0, standalone=True, gamma=GAMMA)
    nxt = step(env, RIGHT)["next"]
    assert col(nxt["reward"]) == [0.0]
    assert col(nxt["terminated"]) == [True]
    assert col(nxt["done"]) == [True]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"gamma": 0.0},
        {"gamma": -0.5},
        {"gamma": 1.01},
        {"train_stage": -1},
        {"train_stage": 2},
        {"train_stage": 5},
    ],
)
def test_invalid_arguments(kwargs):
    base = GridWorldEnv((1,), size=10, num_stages=2)
    with pytest.raises(ValueError):
        StageTransform(base.stage_fn, 2, **kwargs)


def test_invalid_num_stages():
    with pytest.raises(ValueError):
        StageTransform(lambda td: td["observation"][..., :1].long(), 0)


# ---------------------------------------------------------------------- frozen value module
def test_next_value_is_a_frozen_copy():
    original = linear_value((1.0, 1.0))
    original.module = nn.Sequential(original.module, nn.Dropout(0.5))
    env, _, t = make_env([(3, 4)], train_stage=0, next_value=original, gamma=GAMMA)
    assert t.next_value is not original
    assert all(not p.requires_grad for p in t.next_value.parameters())
    assert all(p.requires_grad for p in original.parameters())
    env.train()
    assert t.training
    assert not any(m.training for m in t.next_value.modules())
    first = step(env, RIGHT)["next", "reward"].item()
    assert first == pytest.approx(GAMMA * (3 + 5) / 5)  # dropout inactive: deterministic
    # changing the original's weights afterwards does not change the transform's output
    with torch.no_grad():
        original.module[0].weight.fill_(10.0)
    env.train()
    assert step(env, RIGHT)["next", "reward"].item() == pytest.approx(first)
    # set_next_value installs a new frozen snapshot
    t.set_next_value(original)
    assert step(env, RIGHT)["next", "reward"].item() == pytest.approx(GAMMA * 10 * 8 / 5)
    assert not any(m.training for m in t.next_value.modules())


def test_freeze_helper():
    lin = nn.Linear(2, 1)
    frozen = freeze(lin)
    assert frozen is not lin and not frozen.training
    assert not frozen.weight.requires_grad and lin.weight.requires_grad
    assert torch.equal(frozen.weight, lin.weight)
    assert frozen.weight.data_ptr() != lin.weight.data_ptr()


def test_next_value_follows_state_dict():
    _, _, t = make_env([(3, 4)], train_stage=0, next_value=linear_value((2.0, 3.0)))
    sd = t.state_dict()
    assert any(k.endswith("weight") for k in sd)
    _, _, t2 = make_env([(3, 4)], train_stage=0, next_value=linear_value((0.0, 0.0)))
    t2.load_state_dict(sd)
    assert torch.equal(t2.next_value.module.weight, torch.tensor([[2.0, 3.0]]))


# ---------------------------------------------------------------------- replay-buffer path
def collect_raw(steps=3, rewrite_in_env=False):
    """Rows start at (0,1) [task-ending transition], (3,1) [transition] and (5,0) [transition
    at the second step] on a 10x10 grid with 5 strips and target (0, 2); always move right.
    Stage 0's episode is cut at the transition (``rewrite_in_env=False``); rewards stay raw."""
    base = GridWorldEnv(
        (3,), size=10, num_stages=5, target=(0, 2), start_cell=[(0, 1), (3, 1), (5, 0)]
    )
    env = TransformedEnv(
        base,
        StageTransform(
            base.stage_fn,
            5,
            train_stage=0,
            next_value=const_value(99.0),
            gamma=GAMMA,
            rewrite_in_env=rewrite_in_env,
        ),
    )
    data = env.rollout(
        steps,
        policy=lambda td: td.set("action", torch.full((3,), RIGHT)),
        break_when_any_done=False,
    )
    return base, data


def expected_view(data, value_fn, gamma=GAMMA):
    """Stage 0's view of raw transitions, computed here from the raw entries."""
    nxt = data["next"]
    leaving = nxt["stage_transition"] & (data["stage"] == 0)
    v = value_fn(nxt["observation"])
    reward = torch.where(leaving & ~nxt["terminated"], nxt["reward"] + gamma * v, nxt["reward"])
    return reward, nxt["terminated"] | leaving


def stage_buffer(data, transform, batch_size=64):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(32), batch_size=batch_size)
    rb.extend(data.reshape(-1))
    rb.append_transform(transform)
    return rb


def test_raw_collection_cuts_the_episode_with_truncated():
    _, data = collect_raw()
    nxt = data["next"]
    # row 0 enters the target each step (reset in between), row 1 transitions each step,
    # row 2 transitions at its second step, then restarts
    assert nxt["stage_transition"].squeeze(-1).tolist() == [
        [True, True, True],
        [True, True, True],
        [False, True, False],
    ]
    assert nxt["reward"].squeeze(-1).tolist() == [[1.0] * 3, [0.0] * 3, [0.0] * 3]
    assert nxt["terminated"].squeeze(-1).tolist() == [[True] * 3, [False] * 3, [False] * 3]
    # the transition ends stage 0's episode for the collector as a truncation ...
    assert nxt["truncated"].squeeze(-1).tolist() == [[True] * 3, [True] * 3, [False, True, False]]
    # ... and done is terminated | truncated on every step the package emits
    assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])


def test_done_is_terminated_or_truncated_with_rewrite_in_env():
    _, data = collect_raw(rewrite_in_env=True)
    nxt = data["next"]
    assert torch.equal(nxt["done"], nxt["terminated"] | nxt["truncated"])
    assert nxt["terminated"].squeeze(-1).tolist() == [[True] * 3, [True] * 3, [False, True, False]]


@pytest.mark.parametrize("rewrite_in_env", [True, False])
def test_leaving_stage_k_counts_as_solved_in_both_modes(rewrite_in_env):
    # the grid world writes no success flag: with rewrite_in_env leaving stage 0 terminates,
    # without it the transform writes the flag (leaving is then a truncation)
    base, data = collect_raw(rewrite_in_env=rewrite_in_env)
    nxt = data["next"]
    done_rows = nxt["done"].squeeze(-1).tolist()
    assert done_rows == [[True] * 3, [True] * 3, [False, True, False]]
    assert ended_well(data).squeeze(-1).tolist() == done_rows
    assert episode_stats(data).success.tolist() == [True, True, True]
    assert ("success" in nxt.keys()) is not rewrite_in_env
    env = TransformedEnv(
        base, StageTransform(base.stage_fn, 5, train_stage=0, standalone=True, rewrite_in_env=False)
    )
    check_env_specs(env, seed=0)  # the flag it writes is declared


def test_reward_transform_gives_stage_k_view_at_sampling_time():
    _, data = collect_raw()
    flat = data.reshape(-1)
    rb = stage_buffer(data, StageRewardTransform(0, 5, next_value=cell_sum_value(), gamma=GAMMA))
    view = rb[:]
    reward, terminated = expected_view(flat, lambda o: o.sum(-1, keepdim=True) * 5)
    assert torch.allclose(view["next", "reward"], reward)
    assert torch.equal(view["next", "terminated"], terminated)
    assert torch.equal(view["next", "done"], terminated | view["next", "truncated"])
    # by hand: row 1 transitions into (3, 2): V = 5 -> 4.5; the task-ending row 0 keeps r = 1
    by_row = view["next", "reward"].reshape(3, 3)
    assert by_row[0].tolist() == [1.0, 1.0, 1.0]
    assert by_row[1].tolist() == pytest.approx([GAMMA * 5] * 3)
    assert by_row[2].tolist() == pytest.approx([0.0, GAMMA * 7, 0.0])
    # the storage stays raw, also after indexing and sampling
    sample = rb.sample()
    raw = rb.storage[torch.arange(9)]
    assert torch.equal(raw["next", "reward"], flat["next", "reward"])
    assert torch.equal(raw["next", "terminated"], flat["next", "terminated"])
    s_reward, s_term = expected_view(sample, lambda o: o.sum(-1, keepdim=True) * 5)
    assert torch.allclose(sample["next", "reward"], s_reward)
    assert torch.equal(sample["next", "terminated"], s_term)


def test_sampled_reward_follows_the_next_network_after_storage():
    _, data = collect_raw()
    v_next = linear_value((0.0, 0.0), bias=1.0)  # the next stage's network, by reference
    rb = stage_buffer(data, StageRewardTransform(0, 5, next_value=v_next, gamma=GAMMA))
    before = rb[:]["next", "reward"].reshape(3, 3)
    assert before[1].tolist() == pytest.approx([GAMMA * 1.0] * 3)
    with torch.no_grad():  # the next stage learns after the data was stored
        v_next.module.bias.fill_(10.0)
    after = rb[:]["next", "reward"].reshape(3, 3)
    assert after[1].tolist() == pytest.approx([GAMMA * 10.0] * 3)
    assert after[0].tolist() == [1.0, 1.0, 1.0]  # task-terminating transitions: never a V term
    assert after[2].tolist() == pytest.approx([0.0, GAMMA * 10.0, 0.0])
    assert torch.equal(
        rb.storage[torch.arange(9)]["next", "reward"], data.reshape(-1)["next", "reward"]
    )


def test_reward_transform_without_next_value_only_marks_the_transition():
    _, data = collect_raw()
    rb = stage_buffer(data, StageRewardTransform(0, 5, standalone=True, gamma=GAMMA))
    view = rb[:]
    assert torch.equal(view["next", "reward"], data.reshape(-1)["next", "reward"])
    _, terminated = expected_view(data.reshape(-1), lambda o: o[..., :1] * 0)
    assert torch.equal(view["next", "terminated"], terminated)


@pytest.mark.parametrize(
    ("drop", "missing"),
    [("stage", "needs stage"), (("next", "stage_transition"), "needs next.stage_transition")],
)
def test_reward_transform_names_missing_entries(drop, missing):
    _, data = collect_raw()
    rb = stage_buffer(data.exclude(drop), StageRewardTransform(0, 5, next_value=const_value(1.0)))
    with pytest.raises(KeyError, match=missing):
        rb.sample()


def test_reward_transform_refuses_env_use():
    base = GridWorldEnv((1,), size=10, num_stages=2)
    env = TransformedEnv(base, StageRewardTransform(1, 2))
    with pytest.raises(RuntimeError, match="replay-buffer transform"):
        env.reset()


def test_stage_transform_refuses_replay_buffer_use():
    base, data = collect_raw()
    rb = stage_buffer(data, StageTransform(base.stage_fn, 5))
    with pytest.raises(RuntimeError, match="StageRewardTransform"):
        rb.sample()


def test_reward_transform_arguments():
    with pytest.raises(ValueError, match="next_value"):
        StageRewardTransform(0, 2)  # stage 0 has a next stage
    with pytest.raises(ValueError, match="last"):
        StageRewardTransform(1, 2, next_value=const_value(1.0))
    with pytest.raises(ValueError, match="outside"):
        StageRewardTransform(2, 2)


def test_stage_skip_with_a_next_value_is_an_error():
    # a 3-strip grid whose stage function jumps from stage 0 to stage 2
    base = GridWorldEnv((1,), size=9, num_stages=3, start_cell=(0, 2))

    def skipping(td):
        stage = base.stage_fn(td)
        return torch.where(stage == 1, torch.full_like(stage, 2), stage)

    env = TransformedEnv(
        base, StageTransform(skipping, 3, train_stage=0, next_value=const_value(1.0))
    )
    with pytest.raises(ValueError, match="landed in stage 2"):
        step(env, RIGHT)


def test_stage_fn_outside_the_stages_is_an_error():
    base = GridWorldEnv((1,), size=10, num_stages=2)
    env = TransformedEnv(base, StageTransform(lambda td: base.stage_fn(td) + 5, 2))
    with pytest.raises(ValueError, match="outside 0..1"):
        env.reset()


def test_train_stage_without_next_value_needs_standalone():
    base = GridWorldEnv((1,), size=10, num_stages=2)
    with pytest.raises(ValueError, match="standalone"):
        StageTransform(base.stage_fn, 2, train_stage=0)
    StageTransform(base.stage_fn, 2, train_stage=0, standalone=True)  # asked for explicitly


class _SelfTaggedGrid(GridWorldEnv):
    """A grid world whose own output carries its stage (like envs that track it in dynamics)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.observation_spec["stage"] = Categorical(
            self.num_stages, shape=(*self.batch_size, 1), dtype=torch.int64
        )

    def _reset(self, tensordict, **kwargs):
        out = super()._reset(tensordict, **kwargs)
        return out.set("stage", self.stage_fn(out))

    def _step(self, tensordict):
        out = super()._step(tensordict)
        return out.set("stage", self.stage_fn(out))


def test_stage_fn_none_reads_the_envs_own_stage_entry():
    base = _SelfTaggedGrid((3,), start_cell=(2, 4))
    env = TransformedEnv(base, StageTransform(None, base.num_stages))
    check_env_specs(env)
    td = env.reset()
    td["action"] = torch.tensor([3, 1, 3])  # right (into stage 1), down, right
    td = env.step(td)
    assert td["next", "stage"].squeeze(-1).tolist() == [1, 0, 1]
    assert td["next", "stage_transition"].squeeze(-1).tolist() == [True, False, True]
