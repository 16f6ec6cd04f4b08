"""The cargo task end to end: config, CNN learners, the continuous -> discrete switch, a CLI run."""

from __future__ import annotations

import json

import pytest
import torch
from helpers import assert_figure, hydra_config
from tensordict.nn import TensorDictModule
from torchrl.data import Bounded, Categorical

from torchrl_stages.config import ConfigError
from torchrl_stages.evaluate import rollout_first_episodes
from torchrl_stages.learners import make_learner
from torchrl_stages.learners.dqn import DQNLearner
from torchrl_stages.learners.networks import ConvEncoder
from torchrl_stages.learners.td3 import TD3Learner
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.runs.experiment import build_task


@pytest.fixture(scope="module")
def compose_cfg():
    with hydra_config("task=cargo") as compose_fn:
        yield compose_fn


@pytest.fixture(scope="module")
def task(compose_cfg):
    return build_task(compose_cfg())


def test_td3_slider_then_dqn_propelled(compose_cfg, task):
    cfg = compose_cfg()
    assert list(cfg.task.stages) == ["slider", "propelled"]
    assert [cfg.task.stages[k].algo for k in ("slider", "propelled")] == ["td3", "dqn"]
    s0, s1 = task.specs(0), task.specs(1)
    assert s0.action_key == ("slider", "action") and isinstance(s0.action_spec, Bounded)
    assert s1.action_key == ("propelled", "action") and isinstance(s1.action_spec, Categorical)
    assert s0.observation_keys == ["window", "target"]
    assert s0.input_shapes == [(1, 10, 10), (2,)] and s0.observation_dim == 2


def test_learners_read_the_window_through_a_cnn(compose_cfg, task):
    cfg = compose_cfg()
    learners = [make_learner(task.stage_cfg(k), task.specs(k)) for k in (0, 1)]
    assert isinstance(learners[0], TD3Learner) and isinstance(learners[1], DQNLearner)
    for learner in learners:
        convs = [m for m in learner.modules() if isinstance(m, ConvEncoder)]
        assert convs and all(c.out_features == 16 * 3 * 3 for c in convs)
    td = task.stage_env(1, 4).reset()
    out = learners[1].policy(td)
    assert out["propelled", "action"].shape == (4,)
    assert out["action_value"].shape == (4, 2)
    assert cfg.task.stages.propelled.dueling


def test_ddpg_on_the_slider_composes_and_dqn_is_refused(compose_cfg):
    # the slider block sets keys DDPG and TD3 share, so DDPG composes and builds ...
    assert build_task(compose_cfg("algo@task.stages.slider=ddpg")).num_stages == 2
    # ... and DQN is refused before training, naming the key it lacks
    with pytest.raises(ConfigError, match=r"^task\.stages\.slider\.actor_lr=.*not a key of dqn"):
        build_task(compose_cfg("algo@task.stages.slider=dqn"))


def test_ddpg_on_the_propelled_robot_is_refused(compose_cfg):
    # the propelled block sets only shared keys: DDPG composes, and validation refuses it
    with pytest.raises(ConfigError, match=r"task.stages.propelled.algo='ddpg'.*Fix:"):
        build_task(compose_cfg("algo@task.stages.propelled=ddpg"))


@pytest.mark.parametrize(
    "overrides",
    [["task.stages.slider.cnn_channels=[8]"], ["task.stages.propelled.cnn_kernels=[3,0]"]],
)
def test_bad_cnn_configs_are_refused(compose_cfg, overrides):
    with pytest.raises(ConfigError, match=r"cnn_.*Fix:"):
        build_task(compose_cfg(*overrides))


@pytest.mark.parametrize("robot, dropped", [("propelled", "slider"), ("slider", "propelled")])
def test_single_robot_baselines(compose_cfg, robot, dropped):
    cfg = compose_cfg(f"task.env.robots=[{robot}]", f"~task.stages.{dropped}")
    task = build_task(cfg)
    assert task.num_stages == 1 and task.specs(0).action_key == (robot, "action")
    rollout = task.stage_env(0, 4).rollout(40)
    assert rollout["stage"].max() == 0 and (rollout["position"][..., 0] < 35).all()


def test_robots_and_stages_must_match(compose_cfg):
    with pytest.raises(ConfigError, match=r"task\.stages.*1 stages but 2"):
        build_task(compose_cfg("task.env.robots=[propelled]"))


def test_transition_reward_uses_the_propelled_value_at_the_handover(task):
    # V_1 reads the target ahead-coordinate the second robot sees after the handover
    v1 = TensorDictModule(lambda t: t[..., :1] + 10.0, ["target"], ["state_value"])
    env = task.stage_env(0, batch_size=2, next_value=v1)
    base = env.base_env
    env.reset()
    td = base.set_state([[33.5, 2.0], [20.0, 2.0]], heading=0.0)
    td.set("episode_reward", torch.zeros(2, 1))
    td["slider", "action"] = torch.zeros(2, 1)
    out = env.step(td)["next"]
    gamma = float(task.stage_cfg(0).gamma)
    assert out["stage"].squeeze(-1).tolist() == [1, 0]
    assert out["terminated"].squeeze(-1).tolist() == [True, False]
    assert out["reward"][0].item() == pytest.approx(gamma * (out["target"][0, 0].item() + 10.0))
    assert out["reward"][1].item() == 0.0


def test_stacked_policy_switches_from_continuous_to_discrete_mid_episode(task):
    """A batched whole-task episode: the slider (continuous) acts until the cargo crosses the
    line, then the self-propelled robot (discrete) does; each acts only on its own elements."""
    turn = TensorDictModule(lambda t: t[..., 1:2].clamp(-1, 1), ["target"], [("slider", "action")])
    propel = TensorDictModule(
        lambda t: (t[..., 0] > 0).long(), ["target"], [("propelled", "action")]
    )
    policy = StackedPolicy([turn, propel])
    env = task.task_env(16)
    env.set_seed(0)
    base = env.base_env
    rollout = rollout_first_episodes(env, policy, 40)
    stage = rollout["stage"].squeeze(-1)  # [16, T]
    switched = (stage[:, 0] == 0) & (stage == 1).any(-1)
    assert switched.any(), "no element handed the cargo over within 40 steps"
    slider = rollout["slider", "action"].squeeze(-1)
    propelled = rollout["propelled", "action"]
    assert slider.dtype == torch.float32 and propelled.dtype == torch.int64
    assert (propelled[stage == 0] == 0).all() and (slider[stage == 1] == 0).all()
    assert (slider[stage == 0] != 0).any() and (propelled[stage == 1] == 1).any()
    # stage 1 steps move only when propelled (up to noise): displacement ~2 a vs ~0.23 a
    moved = (rollout["next", "position"] - rollout["position"]).norm(dim=-1)
    on = (stage == 1) & (propelled == 1) & ~rollout["next", "done"].squeeze(-1)
    off = (stage == 1) & (propelled == 0)
    if off.any():
        assert moved[off].max() < 1.0
    assert moved[on].median() > 1.0
    assert base.num_stages == 2


@pytest.mark.e2e
@pytest.mark.slow
def test_tiny_cli_run(train_tiny):
    result, run_dir = train_tiny(
        "cargo", ["slider", "propelled"], "eval.episodes=8", "task.env.max_steps=30"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"Run directory: {run_dir}" in result.stdout
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 8 and result["task_metrics"]["robots"] == ["slider", "propelled"]
    steps = result["mean_steps_per_stage"]  # steps each robot carried the cargo
    assert len(steps) == 2 and sum(steps) == pytest.approx(result["mean_steps"])
    assert 0 < result["mean_steps"] <= 30
    assert_figure(run_dir / "cargo.png")
    assert (run_dir / "stage_0.pt").is_file() and (run_dir / "stage_1.pt").is_file()
