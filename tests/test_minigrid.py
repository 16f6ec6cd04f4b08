"""The MiniGrid task family: its stage function, its stage-k starts, its vector env and a run
from the command line. Skipped, with the reason, where the ``minigrid`` extra is missing."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import assert_figure, run_cli

MISSING = "the minigrid extra is not installed: pip install '.[minigrid]'"
pytest.importorskip("minigrid", reason=MISSING)

import gymnasium  # noqa: E402

from torchrl_stages.config import ConfigError  # noqa: E402
from torchrl_stages.envs.minigrid import (  # noqa: E402
    BLOCKER,
    DOORS,
    FEATURES,
    MiniGridEnv,
    StagedMiniGrid,
    stage_names,
)
from torchrl_stages.envs.minigrid.env import VIEW  # noqa: E402
from torchrl_stages.runs.experiment import build_task  # noqa: E402

LEVELS = ["MiniGrid-DoorKey-5x5-v0", "MiniGrid-KeyCorridorS3R1-v0", "MiniGrid-UnlockPickup-v0"]
DIRECTIONS = [(1, 0), (0, 1), (-1, 0), (0, -1)]  # MiniGrid's agent_dir 0..3


def _face(env: StagedMiniGrid, cell) -> None:
    """Puts the agent next to ``cell``, facing it: on a free cell, else in an unlocked door
    (opened; KeyCorridorS3R1's rooms are one cell, reached from their door)."""
    level = env.unwrapped
    for doors in (False, True):
        for d, (dx, dy) in enumerate(DIRECTIONS):
            x, y = int(cell[0]) - dx, int(cell[1]) - dy
            if not (0 < x < level.width and 0 < y < level.height):
                continue
            there = level.grid.get(x, y)
            door = doors and there is not None and there.type == "door" and not there.is_locked
            if there is None or door:
                if door:
                    there.is_open = True
                level.agent_pos, level.agent_dir = np.array([x, y]), d
                return
    raise AssertionError(f"no free cell next to {cell}")


@pytest.mark.parametrize("level", LEVELS)
def test_the_level_steps_as_before_without_drawing_its_own_view(level):
    # the wrapper's features replace the level's image: the level no longer draws it, and
    # its states, rewards and ends are those of the level as it ships (same seed, same actions;
    # these never toggle UnlockPickup's box, which the wrapper keeps from breaking)
    env, shipped = StagedMiniGrid(gymnasium.make(level)), gymnasium.make(level).unwrapped
    env.reset(seed=5)
    shipped.reset(seed=5)
    actions = np.random.default_rng(0).integers(len(env.actions), size=300)
    for action in actions:
        _, reward, terminated, truncated, _ = env.step(action)
        out = shipped.step(env.unwrapped.actions[env.actions[action]])
        assert (reward > 0, terminated, truncated) == (out[1] > 0, out[2], out[3])
        level = env.unwrapped
        assert tuple(level.agent_pos) == tuple(shipped.agent_pos)
        assert (level.agent_dir, level.step_count) == (shipped.agent_dir, shipped.step_count)
        assert (level.carrying is None) == (shipped.carrying is None)
        if terminated or truncated:
            break
    assert not env.unwrapped.gen_obs()["image"].any() and out[0]["image"].any()


@pytest.mark.parametrize("level", LEVELS)
def test_the_stage_follows_the_level_and_never_goes_back(level):
    env = StagedMiniGrid(gymnasium.make(level))
    obs, _ = env.reset(seed=3)
    assert obs["stage"].tolist() == [0] and obs["observation"].shape == (len(env.features),)
    _face(env, env.plan.key.cur_pos)
    obs, reward, *_ = env.step(env.action("pickup"))
    assert obs["stage"].tolist() == [1] and reward == 0.0  # the key is carried
    _face(env, env.plan.door.cur_pos)
    obs, *_ = env.step(env.action("toggle"))
    assert obs["stage"].tolist() == [2] and env.plan.door.is_open  # the key opened the door
    obs, *_ = env.step(env.action("toggle"))  # closing the door again
    assert obs["stage"].tolist() == [2] and not env.plan.door.is_open
    env.step(env.action("toggle"))
    level_env = env.unwrapped
    level_env.carrying = None  # as if it had dropped the key
    target = env.plan.target
    if target.type == "goal":
        _face(env, target.cur_pos)
        obs, reward, terminated, truncated, _ = env.step(env.action("forward"))
    else:
        _face(env, target.cur_pos)
        obs, reward, terminated, truncated, _ = env.step(env.action("pickup"))
    assert obs["stage"].tolist() == [2] and terminated and reward == 1.0 and not truncated


def test_a_blocked_door_and_a_key_in_a_box_are_stages_of_their_own():
    env = StagedMiniGrid(gymnasium.make("MiniGrid-ObstructedMaze-1Dlhb-v0"))
    obs, _ = env.reset(seed=1)
    plan, level = env.plan, env.unwrapped

    def features() -> dict[str, float]:
        return dict(zip(env.features, obs["observation"].tolist(), strict=True))

    size = max(level.width, level.height)
    box = (np.array(plan.box.cur_pos) - level.agent_pos) / size  # the key hides in its box
    assert (features()["key_dx"], features()["key_dy"]) == pytest.approx(tuple(box))
    _face(env, plan.blocked)
    obs, *_ = env.step(env.action("pickup"))
    assert obs["stage"].tolist() == [0] and features()["carries_blocker"] == 1.0  # not put down
    free = next(
        (x, y)
        for y in range(1, level.height - 1)
        for x in range(1, 5)
        if (x, y) != plan.blocked and level.grid.get(x, y) is None
    )
    _face(env, free)
    obs, *_ = env.step(env.action("drop"))
    assert obs["stage"].tolist() == [1] and level.grid.get(*free) is plan.blocker
    _face(env, plan.box.cur_pos)
    obs, *_ = env.step(env.action("toggle"))  # the box opens: the key lies where it was
    assert obs["stage"].tolist() == [1] and features()["front_key"] == 1.0
    obs, *_ = env.step(env.action("pickup"))
    assert obs["stage"].tolist() == [2] and level.carrying is plan.key
    _face(env, plan.door.cur_pos)
    obs, *_ = env.step(env.action("toggle"))
    assert obs["stage"].tolist() == [3] and plan.door.is_open
    level.carrying = None  # as if it had dropped the key
    _face(env, plan.target.cur_pos)
    obs, reward, terminated, *_ = env.step(env.action("pickup"))
    assert obs["stage"].tolist() == [3] and terminated and reward == 1.0
    for stage in range(4):  # starts inside each stage: every earlier goal done
        env = StagedMiniGrid(gymnasium.make("MiniGrid-ObstructedMaze-1Dlhb-v0"), stage)
        for seed in (0, 1, 2, 807):  # 807: the ball and the box wall the agent's start in
            obs, _ = env.reset(seed=seed)
            plan, level = env.plan, env.unwrapped
            assert obs["stage"].tolist() == [stage]
            moved = level.grid.get(*plan.blocked) is None and level.carrying is not plan.blocker
            assert moved == (stage >= 1) and (level.carrying is plan.key) == (stage >= 2)
            assert (level.grid.get(*plan.box.cur_pos) is plan.box) == (stage < 2)
            assert plan.door.is_open == (stage == 3)


def test_the_box_does_not_break_so_that_every_termination_is_a_success():
    # in UnlockPickup itself, a toggled box is replaced by its (empty) contents and the level
    # can no longer be solved; evaluations count every termination as a success, so the
    # wrapper never ends an episode failed: the toggle leaves the box be
    level = gymnasium.make("MiniGrid-UnlockPickup-v0")
    level.reset(seed=0)
    box = level.unwrapped.obj
    assert box.toggle(level.unwrapped, box.cur_pos)  # MiniGrid's own box opens
    env = StagedMiniGrid(gymnasium.make("MiniGrid-UnlockPickup-v0"), start_stage=2)
    env.reset(seed=0)
    _face(env, env.plan.target.cur_pos)
    for _ in range(3):
        obs, reward, terminated, truncated, _ = env.step(env.action("toggle"))
        assert not terminated and reward == 0.0
        assert env.unwrapped.grid.get(*env.plan.target.cur_pos) is env.plan.target
    env.unwrapped.carrying = None  # as if it had dropped the key
    obs, reward, terminated, truncated, _ = env.step(env.action("pickup"))
    assert terminated and reward == 1.0  # still there to pick up
    # a ball (KeyCorridor) cannot be broken: toggling it changes nothing
    env = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R1-v0"), start_stage=2)
    env.reset(seed=0)
    _face(env, env.plan.target.cur_pos)
    assert not env.step(env.action("toggle"))[2]


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("stage", [0, 1, 2])
def test_episodes_start_inside_the_stage_where_the_agent_can_stand(level, stage):
    env = StagedMiniGrid(gymnasium.make(level), start_stage=stage)
    cells = set()
    for seed in range(8):
        obs, _ = env.reset(seed=seed)
        level_env = env.unwrapped
        assert obs["stage"].tolist() == [stage]
        assert (level_env.carrying is env.plan.key) == (stage >= 1)
        assert env.plan.door.is_open == (stage == 2) and env.plan.door.is_locked == (stage < 2)
        there = level_env.grid.get(*level_env.agent_pos)  # a free cell or an open doorway
        assert there is None or (there.type == "door" and there.is_open)
        assert np.isfinite(obs["observation"]).all() and np.abs(obs["observation"]).max() <= 1
        cells.add(tuple(level_env.agent_pos))
    assert stage == 0 or len(cells) > 1  # drawn (stage 0 of DoorKey: the level's own start)


def test_stage_starts_cover_open_rooms_and_doorways():
    # KeyCorridor hands over in a doorway, with the doors it went through open: the starts of
    # the next stage must hold such states
    env = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=1)
    doorway, open_doors = 0, set()
    for seed in range(200):
        env.reset(seed=seed)
        level = env.unwrapped
        doors = [o for o in level.grid.grid if o is not None and o.type == "door"]
        open_doors.add(sum(d.is_open for d in doors if d is not env.plan.door))
        there = level.grid.get(*level.agent_pos)
        doorway += there is not None and there.type == "door"
        assert env.plan.door.is_locked and not env.plan.door.is_open  # stage 1: still locked
    assert doorway > 0 and len(open_doors) > 2


def test_stage_0_starts_spread_over_the_rooms_only_where_the_level_has_rooms():
    # KeyCorridor's own start is the corridor: stage 0 draws its starts over every room it can
    # reach; DoorKey's own start already is a uniform cell of the key's room, and is kept
    corridor = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=0)
    own = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"))
    columns, own_columns = set(), set()
    for seed in range(40):
        corridor.reset(seed=seed)
        own.reset(seed=seed)
        room = corridor.unwrapped.room_size - 1
        columns.add(int(corridor.unwrapped.agent_pos[0]) // room)
        own_columns.add(int(own.unwrapped.agent_pos[0]) // room)
        assert corridor.unwrapped.carrying is None and corridor.stage == 0
    assert own_columns == {1} and columns == {0, 1, 2}  # the side rooms too
    doorkey = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-8x8-v0"), start_stage=0)
    level = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-8x8-v0"))
    for seed in range(5):
        doorkey.reset(seed=seed)
        level.reset(seed=seed)
        assert tuple(doorkey.unwrapped.agent_pos) == tuple(level.unwrapped.agent_pos)
        assert doorkey.unwrapped.agent_dir == level.unwrapped.agent_dir


def test_view_doors_adds_where_the_doors_around_the_agent_are():
    # a closed door is as blocked as a wall in blocked_*: door_* tells them apart
    plain = StagedMiniGrid(
        gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=0, view_doors=False
    )
    doors = StagedMiniGrid(
        gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=0, view_doors=True
    )
    assert doors.features == FEATURES + DOORS and len(DOORS) == (2 * VIEW + 1) ** 2
    assert doors.observation_space["observation"].shape == (len(FEATURES) + len(DOORS),)
    seen_closed = False
    for seed in range(6):
        a, _ = plain.reset(seed=seed)
        b, _ = doors.reset(seed=seed)
        for step in range(30):
            # the features before are the plain observation's, unchanged
            np.testing.assert_array_equal(a["observation"], b["observation"][: len(FEATURES)])
            level = doors.unwrapped
            ax, ay = (int(v) for v in level.agent_pos)
            for i, name in enumerate(DOORS):
                dx, dy = (int(v) for v in name.split("_")[1:])
                x, y = ax + dx, ay + dy
                inside = 0 <= x < level.width and 0 <= y < level.height
                cell = level.grid.get(x, y) if inside else None
                is_door = cell is not None and cell.type == "door"
                assert b["observation"][len(FEATURES) + i] == float(is_door)
                blocked = b["observation"][FEATURES.index(f"blocked_{dx}_{dy}")]
                seen_closed |= is_door and not cell.is_open and blocked == 1.0
            action = (seed + 3 * step) % doors.action_space.n
            a = plain.step(action)[0]
            b = doors.step(action)[0]
    assert seen_closed
    env = MiniGridEnv("MiniGrid-KeyCorridorS3R1-v0", batch_size=(2,))  # rooms: doors in view
    try:
        assert env.reset()["observation"].shape == (2, len(FEATURES) + len(DOORS))
    finally:
        env.close()


def test_no_op_reward_is_paid_for_actions_that_change_nothing_only():
    env = StagedMiniGrid(
        gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=0, no_op_reward=-0.1
    )
    plain = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R3-v0"), start_stage=0)
    paid = 0
    for seed in range(4):
        env.reset(seed=seed)
        plain.reset(seed=seed)
        for step in range(60):
            level = env.unwrapped
            front = level.grid.get(*level.front_pos)
            action = env.actions[(seed + 5 * step) % env.action_space.n]
            # MiniGrid changes nothing for these (the key stage carries nothing yet)
            nothing = (
                (action == "forward" and front is not None and not front.can_overlap())
                or (action == "pickup" and (front is None or not front.can_pickup()))
                or (
                    action == "toggle"
                    and (front is None or front.type != "door" or front.is_locked)
                )
                or (action == "drop" and level.carrying is None)
            )
            obs, reward, terminated, *_ = env.step(env.action(action))
            base = plain.step(plain.action(action))
            np.testing.assert_array_equal(obs["observation"], base[0]["observation"])
            assert reward == base[1] + (-0.1 if nothing else 0.0), (seed, step, action)
            assert terminated == base[2]  # the episode goes on: exploration is untouched
            paid += nothing
            if terminated or obs["stage"][0] > 0:
                break
    assert paid > 10


def test_the_agent_uses_the_actions_its_family_needs():
    doorkey = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"))
    assert doorkey.actions == ("left", "right", "forward", "pickup", "toggle")
    assert doorkey.action_space.n == 5
    corridor = StagedMiniGrid(gymnasium.make("MiniGrid-KeyCorridorS3R1-v0"))
    assert "drop" in corridor.actions and "done" not in corridor.actions  # the ball needs it
    every = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), actions="all")
    assert every.action_space.n == 7 and every.action("done") == 6
    # an action of the wrapper is the level's action of that name
    env = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), actions=["right", "left"])
    env.reset(seed=0)
    before = env.unwrapped.agent_dir
    env.step(0)
    assert env.unwrapped.agent_dir == (before + 1) % 4
    with pytest.raises(ValueError, match=r"actions=\['jump'\].*Fix: name some of left"):
        StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), actions=["jump"])
    vector = MiniGridEnv("MiniGrid-DoorKey-5x5-v0", batch_size=(2,), actions=["left", "toggle"])
    try:
        assert vector.action_spec.space.n == 2
    finally:
        vector.close()


@pytest.mark.parametrize(
    "level, stages, actions, view_doors",
    [
        ("MiniGrid-DoorKey-16x16-v0", ["key", "door", "goal"], 5, False),
        ("MiniGrid-UnlockPickup-v0", ["key", "door", "box"], 6, False),
        ("MiniGrid-KeyCorridorS6R3-v0", ["key", "door", "ball"], 6, True),
        ("MiniGrid-LockedRoom-v0", ["key", "door", "goal"], 5, True),
        ("MiniGrid-ObstructedMaze-1Dlh-v0", ["key", "door", "ball"], 6, False),
        ("MiniGrid-ObstructedMaze-1Dlhb-v0", ["blocker", "key", "door", "ball"], 6, False),
        ("MiniGrid-BlockedUnlockPickup-v0", ["blocker", "key", "door", "box"], 6, False),
    ],
)
def test_the_stages_come_from_the_levels_objects(level, stages, actions, view_doors):
    # one locked door, its key (maybe in a box), maybe a ball in front of it, and a target
    env = StagedMiniGrid(gymnasium.make(level))
    assert stage_names(level) == env.stage_names == stages and env.num_stages == len(stages)
    assert len(env.actions) == actions and ("drop" in env.actions) == (actions == 6)
    blocker = BLOCKER if stages[0] == "blocker" else ()
    assert env.features == FEATURES + DOORS * view_doors + blocker


@pytest.mark.parametrize(
    "level, why",
    [
        ("MiniGrid-Empty-5x5-v0", "it has 0 locked doors"),
        ("MiniGrid-ObstructedMaze-2Dl-v0", "it has 2 locked doors"),
        ("MiniGrid-Unlock-v0", "it has no object to pick up and 0 goal squares"),
    ],
)
def test_a_level_without_linear_stages_is_refused_saying_why(level, why):
    with pytest.raises(ValueError, match=rf"{level} cannot be staged: {why}.*Fix: pick such"):
        MiniGridEnv(level, batch_size=(1,))


def test_levels_that_are_not_minigrid_ids_are_refused():
    with pytest.raises(ValueError, match=r"not a MiniGrid level.*Fix: pick a MiniGrid"):
        MiniGridEnv("CartPole-v1", batch_size=(1,))
    with pytest.raises(ValueError, match=r"Fix: pick a MiniGrid"):  # never imports a module
        MiniGridEnv("os:MiniGrid-DoorKey-5x5-v0", batch_size=(1,))
    with pytest.raises(ValueError, match=r"start_stage=3 is out of range"):
        StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), start_stage=3)


def test_the_vector_env_restarts_finished_copies_inside_their_stage():
    # (worker processes: tests/test_gym_env.py)
    env = MiniGridEnv("MiniGrid-DoorKey-5x5-v0", batch_size=(4,), start_stage=2, max_steps=6)
    try:
        env.set_seed(0)
        td = env.reset()
        assert td["stage"].squeeze(-1).tolist() == [2, 2, 2, 2] and env.max_steps == 6
        ended = 0
        for _ in range(14):
            td["action"] = env.action_spec.rand()
            out, td = env.step_and_maybe_reset(td)
            ended += int(out["next", "done"].sum())
            assert (td["stage"] == 2).all()  # finished copies restarted inside stage 2
        assert ended >= 4  # every copy ended an episode (6-step limit) and went on
    finally:
        env.close()


def test_an_env_id_of_another_family_is_refused_before_training(compose_cfg):
    cfg = compose_cfg("task=minigrid", "task.env.env_id=CartPole-v1")
    with pytest.raises(ConfigError, match=r"(?s)task\.env: cannot build.*Fix: pick a MiniGrid"):
        build_task(cfg)


def test_the_task_has_three_stages_from_its_template(compose_cfg):
    task = build_task(compose_cfg("task=minigrid"))
    assert list(task.cfg.stages) == ["s0", "s1", "s2"] and task.num_stages == 3
    assert task.specs(0).observation_keys == ["observation"]  # the stage tag is not an input
    rollout = task.stage_env(2, batch_size=2).rollout(3)
    assert (rollout["stage"] == 2).all()
    task.spec_env.close()


@pytest.mark.parametrize(
    "env_id, view_doors, gamma, advantage_learning, eval_episodes",
    [
        ("MiniGrid-KeyCorridorS3R3-v0", True, 0.95, 0.9, 64),
        ("MiniGrid-KeyCorridorS3R1-v0", True, 0.95, 0.9, 64),
        ("MiniGrid-UnlockPickup-v0", False, 0.99, 0.9, 64),
        ("MiniGrid-DoorKey-16x16-v0", False, 0.99, 0.0, 256),
        ("MiniGrid-DoorKey-8x8-v0", False, 0.99, 0.0, 64),
        ("MiniGrid-ObstructedMaze-1Dlhb-v0", False, 0.99, 0.9, 64),
        ("MiniGrid-LockedRoom-v0", True, 0.99, 0.0, 64),
    ],
)
def test_a_levels_settings_come_with_its_id(
    compose_cfg, env_id, view_doors, gamma, advantage_learning, eval_episodes
):
    task = build_task(compose_cfg("task=minigrid", f"task.env.env_id={env_id}"))
    blocker = len(BLOCKER) * (env_id == "MiniGrid-ObstructedMaze-1Dlhb-v0")
    assert _features(task) == len(FEATURES) + len(DOORS) * view_doors + blocker
    for k in range(task.num_stages):
        cfg = task.stage_cfg(k)
        settings = (cfg.gamma, cfg.advantage_learning, cfg.eval_episodes, cfg.algo)
        assert settings == (gamma, advantage_learning, eval_episodes, "dqn")
    task.spec_env.close()


def _features(task) -> int:
    return task.spec_env.observation_spec["observation"].shape[-1]


def test_a_levels_settings_give_way_to_the_command_line(compose_cfg):
    task = build_task(
        compose_cfg(
            "task=minigrid",
            "task.env.env_id=MiniGrid-KeyCorridorS3R3-v0",
            "task.env.view_doors=false",
            "task.stage_template.gamma=0.99",
            "+task.stages.s0.advantage_learning=0",
        )
    )
    assert task.cfg.env.view_doors is False
    assert [(task.stage_cfg(k).gamma, task.stage_cfg(k).advantage_learning) for k in range(3)] == [
        (0.99, 0.0),
        (0.99, 0.9),
        (0.99, 0.9),
    ]
    task.spec_env.close()


def test_the_keycorridor_preset_is_s3r3_with_its_settings(compose_cfg):
    for level in ([], ["task.env.env_id=MiniGrid-KeyCorridorS3R2-v0"]):
        task = build_task(compose_cfg("experiment=minigrid_keycorridor", *level))
        assert task.cfg.env.env_id.startswith("MiniGrid-KeyCorridorS3R")
        assert _features(task) == len(FEATURES) + len(DOORS)
        for k in range(task.num_stages):
            cfg = task.stage_cfg(k)
            assert (cfg.gamma, cfg.advantage_learning, cfg.algo) == (0.95, 0.9, "dqn")
        task.spec_env.close()
    assert task.cfg.env.env_id == "MiniGrid-KeyCorridorS3R2-v0"


@pytest.mark.e2e
@pytest.mark.slow
def test_minigrid_trains_from_the_cli(tmp_path):
    run_dir = tmp_path / "run"
    proc = run_cli(
        [
            "stages-train",
            "task=minigrid",
            "experiment=smoke",
            "task.eval_env.max_steps=64",  # the level's 640: untrained episodes run to the end
            f"hydra.run.dir={run_dir}",
        ],
        cwd=tmp_path,
    )
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    result = json.loads((run_dir / "eval.json").read_text())
    assert result["task_metrics"]["stages"] == ["key", "door", "goal"]
    assert result["episodes"] == 32 and 0.0 <= result["success_rate"] <= 1.0
    assert all((run_dir / f"stage_{k}.pt").is_file() for k in range(3))
    assert_figure(run_dir / "minigrid.png")
    assert torch.isfinite(torch.tensor(result["mean_return"]))
    # a shipped task: its run loads without --trust (the level id is data, never a module)
    again = run_cli(["stages-eval", run_dir], cwd=tmp_path)
    assert again.returncode == 0, (again.stdout + again.stderr)[-3000:]
    assert "task minigrid: success" in again.stdout
