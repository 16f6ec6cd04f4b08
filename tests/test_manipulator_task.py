"""The manipulator task end to end: config, the stage-switch reward, a tiny CLI run."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers import assert_figure, hydra_config
from tensordict.nn import TensorDictModule

from torchrl_stages.config import ConfigError
from torchrl_stages.envs.manipulator import inverse_kinematics
from torchrl_stages.runs.experiment import build_task


@pytest.fixture(scope="module")
def compose_cfg():
    with hydra_config("task=manipulator") as compose_fn:
        yield compose_fn


def test_two_ddpg_stages_and_td3_override(compose_cfg):
    cfg = compose_cfg()
    assert list(cfg.task.stages) == ["coarse", "fine"]
    assert [cfg.task.stages[k].algo for k in ("coarse", "fine")] == ["ddpg", "ddpg"]
    cfg = compose_cfg("algo@task.stages.fine=td3")
    assert cfg.task.stages.fine.algo == "td3"
    task = build_task(cfg)
    assert task.num_stages == 2 and task.specs(1).observation_dim == 6


def test_dqn_stage_on_continuous_actions_is_refused(compose_cfg):
    with pytest.raises(ConfigError, match=r"task\.stages\.fine\.algo.*discrete.*Fix:"):
        build_task(compose_cfg("algo@task.stages.fine=dqn"))


def test_random_target_preset_is_one_override(compose_cfg):
    task = build_task(compose_cfg("task.env.random_target=true"))
    env = task.task_env(64)
    env.reset()  # targets are drawn at reset
    targets = env.base_env.targets
    assert targets.norm(dim=-1).max() <= 2.0 and targets.unique(dim=0).shape[0] > 1


def test_single_stage_baseline_config(compose_cfg):
    cfg = compose_cfg("task.env.u_max=[0.05]", "task.env.scales=[0.5]", "~task.stages.fine")
    task = build_task(cfg)
    assert task.num_stages == 1
    assert task.stage_env(0, 4).rollout(60)["stage"].max() == 0  # never switches


def test_transition_reward_uses_fine_value_of_post_switch_observation(compose_cfg):
    cfg = compose_cfg()
    task = build_task(cfg)
    gamma = float(cfg.task.stages.coarse.gamma)
    # V_fine reads the fine encoding of the target offset: (target - effector) / 0.05
    v_fine = TensorDictModule(lambda obs: obs[..., 4:5] + 10.0, ["observation"], ["state_value"])
    env = task.stage_env(0, batch_size=1, next_value=v_fine)
    base = env.base_env
    target = torch.tensor(base.target)
    # effector 0.21 below the target; one step of theta1 brings it inside 0.2
    start = target + torch.tensor([0.0, -0.21])
    theta = inverse_kinematics(start.unsqueeze(0), True)
    env.reset()
    td = base.set_state(theta)  # carries the env's own "stage" (0: coarse)
    td.set("episode_reward", torch.zeros(1, 1))
    best = None
    for a in ([1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]):
        base.set_state(theta)
        td["action"] = torch.tensor([a])
        out = env.step(td.clone())["next"]
        if out["stage_transition"].item():
            best = out
            break
    assert best is not None, "no coarse step crossed the switch distance"
    obs = best["observation"][0]
    effector = obs[2:4]
    fine_offset = (target - effector) / 0.05
    assert torch.allclose(obs[4:6], fine_offset, atol=1e-4)  # already in the fine encoding
    expected = gamma * (fine_offset[0].item() + 10.0)  # r = 0 (not solved), + gamma * V_fine(s')
    assert best["reward"].item() == pytest.approx(expected, rel=1e-5)
    assert best["terminated"].item() and best["done"].item()


@pytest.mark.e2e
@pytest.mark.slow
def test_tiny_cli_run(train_tiny):
    result, run_dir = train_tiny("manipulator", ["coarse", "fine"], "eval.episodes=8")
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"Run directory: {run_dir}" in result.stdout
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 8 and result["starts"] == "random"
    metrics = result["task_metrics"]
    p50, p90, p99 = metrics["final_distance_p50_p90_p99"]
    assert 0.0 <= p50 <= p90 <= p99 <= 4.0 and not math.isnan(p99)
    assert_figure(run_dir / "manipulator.png")
    assert (run_dir / "stage_0.pt").is_file() and (run_dir / "stage_1.pt").is_file()
