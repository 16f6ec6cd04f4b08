"""The Meta-World task family: its stages, its shaping, its stage-1 starts, its seeding and a run
from the command line. Skipped, with the reason, where the ``metaworld`` extra is missing."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from helpers import run_cli

MISSING = "the metaworld extra is not installed: pip install '.[metaworld]'"
pytest.importorskip("metaworld", reason=MISSING)

from torchrl_stages.envs.metaworld import MetaWorldEnv, StagedMetaWorld, make_task  # noqa: E402

GAMMA = 0.99


def _staged(start_stage=None, name="pick-place-v3", **kwargs) -> StagedMetaWorld:
    return StagedMetaWorld(make_task(name), name, start_stage, gamma=GAMMA, **kwargs)


def _scripted_episode(env: StagedMetaWorld, seed: int):
    """The task's scripted policy from a seeded reset: rewards, stages, whether it succeeded."""
    obs, _ = env.reset(seed=seed)
    rewards, stages = [], [int(obs["stage"][0])]
    for _ in range(200):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            action = env.scripted.get_action(obs["observation"].astype(np.float64))
        obs, reward, terminated, truncated, _ = env.step(action)
        rewards.append(reward)
        stages.append(int(obs["stage"][0]))
        if terminated or truncated:
            return rewards, stages, terminated
    return rewards, stages, False


def test_the_shaping_adds_up_to_the_sparse_return_less_the_start_potential():
    env = _staged()
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        start_potential = env.potential
        rewards, stages, success = _scripted_episode(env, seed)
        assert success and stages[0] == 0 and stages[-1] == 1
        assert stages == sorted(stages)  # grasp, then place, never back
        discounted = sum(GAMMA**t * r for t, r in enumerate(rewards))
        expected = -start_potential + GAMMA ** (len(rewards) - 1)
        assert discounted == pytest.approx(expected, abs=1e-9)
    env.close()


def test_a_stage_one_start_holds_the_object_with_its_clock_at_zero():
    env = _staged(start_stage=1)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        level = env.unwrapped
        _, info = level.evaluate_state(obs["observation"].astype(np.float64), np.zeros(4))
        assert int(obs["stage"][0]) == 1 and info["grasp_success"] and not info["success"]
        assert level.curr_path_length == 0
        _, stages, success = _scripted_episode(env, seed)
        assert success and set(stages) == {1}
    env.close()


def test_copies_draw_their_own_placements_and_a_seed_repeats_them():
    env = MetaWorldEnv("pick-place-v3", batch_size=(4,))
    env.set_seed(3)
    first = env.reset()["observation"][:, 4:7]
    env.set_seed(3)
    again = env.reset()["observation"][:, 4:7]
    env.close()
    assert (first == again).all()
    assert len({tuple(row.tolist()) for row in first}) > 1


def test_a_copy_loaded_from_a_state_dict_goes_on_bitwise():
    # a resumed run rebuilds each copy's running episode (its stage-1 start drawn by the
    # scripted policy too) from the generator state and the actions since its reset
    env = MetaWorldEnv("pick-place-v3", batch_size=(2,), start_stage=1)
    env.set_seed(5)
    td = env.reset()
    for _ in range(20):
        td = env.step(env.rand_action(td))["next"]
    state, actions = env.state_dict(), [env.rand_action(td.clone())["action"] for _ in range(5)]
    twin = MetaWorldEnv("pick-place-v3", batch_size=(2,), start_stage=1)
    twin.set_seed(99)
    twin.reset()
    twin.load_state_dict(state)
    assert twin.episodes_rebuilt
    for action in actions:
        ours, theirs = (e.step(td.clone().set("action", action))["next"] for e in (env, twin))
        assert torch.equal(ours["observation"], theirs["observation"])
        assert torch.equal(ours["reward"], theirs["reward"])
    env.close()
    twin.close()


def test_an_unknown_task_is_refused_with_the_names_to_pick_from():
    with pytest.raises(ValueError, match="not a Meta-World v3 task. Fix: .*pick-place-v3"):
        MetaWorldEnv("pick-and-drop-v3", batch_size=(2,))


@pytest.mark.e2e
@pytest.mark.slow
def test_metaworld_trains_from_the_cli(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_cli(
        [
            "stages-train",
            "task=metaworld",
            "experiment=smoke",
            "eval.episodes=4",
            "all_stages.num_envs=4",
            "all_stages.eval_episodes=4",
            "task.stage_template.eval_max_steps=50",
            "task.eval_env.max_episode_steps=50",  # untrained episodes run to the end
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
    )
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["episodes"] == 4 and result["starts"] == "random"
    assert [s["frames"] for s in result["training"]["stages"]] == [1024, 1024]
    # a shipped task: its run loads without --trust (the task's name is data, never a module)
    again = run_cli(["stages-eval", run_dir, "--episodes", "2", "--no-plots"], cwd=tmp_path)
    assert again.returncode == 0, (again.stdout + again.stderr)[-3000:]
    assert "task metaworld: success" in again.stdout
