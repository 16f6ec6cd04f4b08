"""MiniGrid's levels with a locked door as multi-stage tasks: the gymnasium wrapper
:class:`StagedMiniGrid` and the batched :class:`MiniGridEnv`. The stages come from the level's
objects (:class:`LevelPlan`); ``docs/tasks/minigrid.md`` says what each choice is for."""

from __future__ import annotations

import functools
from collections import deque
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch

from torchrl_stages.gym_env import GymStageEnv

from .._common import check_start_stage
from .plan import LevelPlan, UnstageableLevel, probe, refuse, registered_layouts, side

__all__ = [
    "BLOCKER",
    "DOORS",
    "FEATURES",
    "LevelPlan",
    "MiniGridEnv",
    "StagedMiniGrid",
    "UnstageableLevel",
    "import_minigrid",
    "level_actions",
    "stage_names",
]

VIEW = 2  # the local view: the (2 * VIEW + 1)^2 cells around the agent
#: observation features, in order (``(dx, dy)``: offset from the agent, in grid widths)
FEATURES = (
    "x", "y",  # the agent's cell, in grid widths
    "east", "south", "west", "north",  # the direction it faces (one-hot)
    "carries_key", "carries_target",
    "door_open", "door_locked",
    "key_dx", "key_dy", "door_dx", "door_dy", "target_dx", "target_dy",
    # the cell it faces (one-hot)
    "front_free", "front_wall", "front_closed_door", "front_open_door", "front_key",
    "front_target", "front_other",
    *(f"blocked_{dx}_{dy}" for dy in range(-VIEW, VIEW + 1) for dx in range(-VIEW, VIEW + 1)),
)  # fmt: skip
#: the features ``view_doors=True`` appends: which cells around the agent are doors (in
#: ``blocked_*`` a closed door looks like a wall)
DOORS = tuple(f"door_{dx}_{dy}" for dy in range(-VIEW, VIEW + 1) for dx in range(-VIEW, VIEW + 1))
#: the features a level whose door is blocked appends: the blocker carried, where, in front
BLOCKER = ("carries_blocker", "blocker_dx", "blocker_dy", "front_blocker")


def import_minigrid() -> Any:
    """The ``minigrid`` package (importing it registers its levels), or an error with the fix."""
    try:
        import minigrid
    except ImportError as err:
        raise ImportError(
            "task=minigrid needs Farama's MiniGrid. Fix: pip install 'torchrl-stages[minigrid]' "
            f"(or pip install minigrid) ({err})"
        ) from None
    return minigrid


def _check_id(env_id: str) -> None:
    """Refuses an id that is not a registered MiniGrid level (``module:id`` would import)."""
    spec = None if ":" in env_id else gymnasium.registry.get(env_id)
    if spec is None or not str(spec.entry_point).startswith("minigrid."):
        raise UnstageableLevel(
            f"env_id={env_id!r} is not a MiniGrid level. Fix: pick a MiniGrid level id such "
            "as MiniGrid-DoorKey-8x8-v0 (task=gym takes any other gymnasium env with a stage "
            "function of yours)"
        )


def stage_names(env_id: str) -> list[str]:
    """The stages of a level, from its objects.

    Examples:
        >>> stage_names("MiniGrid-KeyCorridorS3R3-v0")
        ['key', 'door', 'ball']
        >>> stage_names("MiniGrid-ObstructedMaze-1Dlhb-v0")
        ['blocker', 'key', 'door', 'ball']
    """
    import_minigrid()
    _check_id(env_id)
    return list(registered_layouts(env_id, ())[0])


def level_actions(env_id: str) -> tuple[str, ...]:
    """The actions a level's stages need.

    Examples:
        >>> level_actions("MiniGrid-DoorKey-16x16-v0")
        ('left', 'right', 'forward', 'pickup', 'toggle')
    """
    import_minigrid()
    _check_id(env_id)
    return registered_layouts(env_id, ())[1]


class StagedMiniGrid(gymnasium.Wrapper):
    """A MiniGrid level with a locked door as a multi-stage task: its stage, features and
    stage-k starts, from the level's objects (:class:`LevelPlan`).

    The stage starts at 0 and moves on by one on the step that completes its goal (blocker
    put down off the door's cell, key carried, door open), never going back; the last stage
    ends on the level's own success. The observation is ``{"observation": float32
    [len(features)], "stage": int64 [1]}`` (:data:`FEATURES`, then :data:`DOORS` with
    ``view_doors``, then :data:`BLOCKER` where the door is blocked); the reward is 1 on success
    (plus ``no_op_reward`` for an action that changes nothing); episodes terminate on success
    only, and a box to pick up cannot be broken. ``actions`` (MiniGrid's names, ``"all"``, or
    ``None``: :attr:`LevelPlan.actions`) are the wrapper's actions, in order; ``view_doors=None``
    turns the doors on where the level has doors that open without a key. ``start_stage=k``
    starts inside stage k: every earlier goal done (blocker moved to a drawn cell, key carried,
    door open), the other doors open at random, the agent on a drawn reachable cell.

    Examples:
        >>> env = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), start_stage=2)
        >>> obs, _ = env.reset(seed=0)
        >>> int(obs["stage"][0]), obs["observation"].shape == (len(FEATURES),)
        (2, True)
        >>> env.unwrapped.carrying.type, env.plan.door.is_open, env.stage_names
        ('key', True, ['key', 'door', 'goal'])
        >>> env.actions, int(env.action_space.n)
        (('left', 'right', 'forward', 'pickup', 'toggle'), 5)
    """

    def __init__(
        self,
        env: gymnasium.Env,
        start_stage: int | None = None,
        actions: Sequence[str] | str | None = None,
        view_doors: bool | None = None,
        no_op_reward: float = 0.0,
    ) -> None:
        super().__init__(env)
        stages, needed, rooms = probe(env.unwrapped)
        _skip_level_image(env.unwrapped)
        self.stage_names = list(stages)
        self.num_stages = len(stages)
        self.start_stage = check_start_stage(start_stage, self.num_stages)
        self.actions = _actions(needed, actions, env.unwrapped.actions)
        self._level_actions = [int(env.unwrapped.actions[name]) for name in self.actions]
        self.action_space = gymnasium.spaces.Discrete(len(self.actions))
        self.view_doors = rooms if view_doors is None else bool(view_doors)
        self.no_op_reward = float(no_op_reward)
        self.features = FEATURES + (DOORS if self.view_doors else ())
        self.features += BLOCKER if stages[0] == "blocker" else ()
        self.observation_space = gymnasium.spaces.Dict(
            observation=gymnasium.spaces.Box(-1.0, 1.0, (len(self.features),), np.float32),
            stage=gymnasium.spaces.Box(0, self.num_stages - 1, (1,), np.int64),
        )
        self.plan: LevelPlan | None = None  # the layout's, from each reset
        self.stage = 0

    def action(self, name: str) -> int:
        """The wrapper's index of the level's action ``name``."""
        return self.actions.index(name)

    def _done(self, stage: int) -> bool:
        """Whether stage ``stage``'s goal holds (the last stage's is the level's success)."""
        plan, carrying = self.plan, self.env.unwrapped.carrying
        name = self.stage_names[stage]
        if name == "blocker":
            return carrying is not plan.blocker and tuple(plan.blocker.cur_pos) != plan.blocked
        if name == "key":
            return carrying is plan.key
        return name == "door" and plan.door.is_open and not plan.door.is_locked

    def _reachable(self) -> list[tuple[int, int]]:
        """The free cells and open doorways the agent can walk to, through doors it can open."""
        level = self.env.unwrapped
        start = tuple(int(v) for v in level.agent_pos)
        seen, queue, cells = {start}, deque([start]), []
        while queue:
            x, y = queue.popleft()
            cell = level.grid.get(x, y)
            if (cell is None or (cell.type == "door" and cell.is_open)) and (x, y) != start:
                cells.append((x, y))
            for nx, ny in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
                if (nx, ny) in seen or not (0 <= nx < level.width and 0 <= ny < level.height):
                    continue
                cell = level.grid.get(nx, ny)
                if cell is None or (cell.type == "door" and not cell.is_locked):
                    seen.add((nx, ny))
                    queue.append((nx, ny))
        return cells + [start]

    def _start_inside(self, stage: int) -> None:
        level, plan, done = self.env.unwrapped, self.plan, self.stage_names[:stage]
        if "blocker" in done:  # put down on a drawn free cell of the agent's side
            start = tuple(int(v) for v in level.agent_pos)
            cells = sorted(side(level, plan.door) - {start, plan.blocked})
            free = [cell for cell in cells if level.grid.get(*cell) is None]
            cell = free[int(self.np_random.integers(len(free)))]
            level.grid.set(*plan.blocked, None)
            level.grid.set(*cell, plan.blocker)
            plan.blocker.cur_pos = np.array(cell)
        if "key" in done:  # the key is carried (the box it hid in, opened, is gone)
            level.grid.set(*(plan.key if plan.box is None else plan.box).cur_pos, None)
            plan.key.cur_pos = np.array([-1, -1])
            level.carrying = plan.key
        if "door" in done:
            plan.door.is_locked, plan.door.is_open = False, True
        # the other doors (KeyCorridor's rooms) open or closed, as an earlier stage may leave them
        for obj in level.grid.grid:
            if (
                obj is not None
                and obj.type == "door"
                and not obj.is_locked
                and obj is not plan.door
            ):
                obj.is_open = bool(self.np_random.integers(2))
        cells = self._reachable()
        level.agent_pos = np.array(cells[int(self.np_random.integers(len(cells)))])
        level.agent_dir = int(self.np_random.integers(4))

    def _features(self) -> np.ndarray:
        level, plan = self.env.unwrapped, self.plan
        size = float(max(level.width, level.height))
        ax, ay = (int(v) for v in level.agent_pos)

        def offset(obj) -> tuple[float, float]:
            pos = obj.cur_pos
            if obj is plan.key and pos is None:  # still in its box, or where the box was
                pos = plan.box.cur_pos
            if pos[0] < 0:  # carried
                return 0.0, 0.0
            return (pos[0] - ax) / size, (pos[1] - ay) / size

        front = level.grid.get(*level.front_pos)
        kinds = np.zeros(7, np.float32)
        if front is None:
            kinds[0] = 1
        elif front.type == "wall":
            kinds[1] = 1
        elif front.type == "door":
            kinds[3 if front.is_open else 2] = 1
        elif front is plan.key:
            kinds[4] = 1
        elif front is plan.target:
            kinds[5] = 1
        else:
            kinds[6] = 1
        blocked, doors = [], []
        for dy in range(-VIEW, VIEW + 1):
            for dx in range(-VIEW, VIEW + 1):
                x, y = ax + dx, ay + dy
                inside = 0 <= x < level.width and 0 <= y < level.height
                cell = level.grid.get(x, y) if inside else None
                blocked.append(float(not inside or (cell is not None and not cell.can_overlap())))
                if self.view_doors:
                    doors.append(float(cell is not None and cell.type == "door"))
        agent = [ax / size, ay / size, *np.eye(4)[level.agent_dir]]
        carrying = level.carrying
        load = [carrying is plan.key, carrying is not None and carrying is plan.target]
        door = [plan.door.is_open, plan.door.is_locked]
        offsets = [*offset(plan.key), *offset(plan.door), *offset(plan.target)]
        blocker = []
        if plan.blocker is not None:
            blocker = [carrying is plan.blocker, *offset(plan.blocker), front is plan.blocker]
        parts = [*agent, *load, *door, *offsets, *kinds, *blocked, *doors, *blocker]
        return np.array(parts, np.float32)

    def _obs(self) -> dict[str, np.ndarray]:
        return {"observation": self._features(), "stage": np.array([self.stage], np.int64)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _, info = self.env.reset(seed=seed, options=options)
        self.plan = plan = LevelPlan.of(self.env.unwrapped)
        if plan.stages != self.stage_names:
            raise refuse(str(self.env.spec and self.env.spec.id), "its layouts differ")
        if plan.target.type == "box":
            plan.target.toggle = _keep_closed  # breaking the box would make it unsolvable
        if self.start_stage is not None and (self.start_stage > 0 or plan.rooms):
            self._start_inside(int(self.start_stage))
        self.stage = 0
        while self.stage < self.num_stages - 1 and self._done(self.stage):
            self.stage += 1
        return self._obs(), info

    def _state(self) -> tuple:
        """What an action can change: the agent's cell, direction and load, and what it faces."""
        level = self.env.unwrapped
        front = level.grid.get(*level.front_pos)
        door = (front.is_open, front.is_locked) if getattr(front, "type", None) == "door" else ()
        position = tuple(int(v) for v in level.agent_pos)
        return position, int(level.agent_dir), id(level.carrying), id(front), door

    def step(self, action):
        before = self._state() if self.no_op_reward else None
        _, reward, terminated, truncated, info = self.env.step(self._level_actions[int(action)])
        if self.stage < self.num_stages - 1 and self._done(self.stage):
            self.stage += 1  # one stage a step: the next stage's value is what it hands on
        reward = float(terminated and reward > 0)
        if before is not None and self._state() == before:
            reward += self.no_op_reward  # an action that changed nothing
        return self._obs(), reward, bool(terminated), bool(truncated), info


def _skip_level_image(level: Any) -> None:
    """Makes ``level`` return a blank image of the same space for its own 7x7 view, which the
    features replace: drawing it was three quarters of a step. Its states are unchanged."""
    space = level.observation_space["image"]

    def gen_obs() -> dict[str, Any]:
        image = np.zeros(space.shape, space.dtype)  # new each call, as gymnasium asks
        return {"image": image, "direction": level.agent_dir, "mission": level.mission}

    level.gen_obs = gen_obs


def _keep_closed(env: Any, pos: Any) -> bool:
    """A box's ``toggle`` that leaves it be (MiniGrid's replaces the box by its contents)."""
    return False


def _actions(
    needed: tuple[str, ...], actions: Sequence[str] | str | None, enum: Any
) -> tuple[str, ...]:
    if actions is None:
        return needed
    names = [a.name for a in enum]
    chosen = tuple(names) if actions == "all" else tuple(str(a) for a in actions)
    unknown = [a for a in chosen if a not in names]
    if unknown or not chosen or len(set(chosen)) != len(chosen):
        raise ValueError(
            f"actions={list(chosen)}: not a list of distinct MiniGrid actions. Fix: name some "
            f"of {', '.join(names)} once each (or 'all'; null: {', '.join(needed)})"
        )
    return chosen


class MiniGridEnv(GymStageEnv):
    """A MiniGrid level (``env_id``) as a batched multi-stage TorchRL env: ``batch_size[0]``
    copies of :class:`StagedMiniGrid` (its keys) in a ``"sync"`` or ``"async"`` gymnasium vector
    env; ``**kwargs`` go to the level (e.g. ``max_steps``).

    Examples:
        >>> env = MiniGridEnv("MiniGrid-DoorKey-5x5-v0", batch_size=(4,), start_stage=1)
        >>> td = env.reset()
        >>> td["stage"].squeeze(-1).tolist(), td["observation"].shape, env.num_stages
        ([1, 1, 1, 1], torch.Size([4, 48]), 3)
        >>> env.close()
    """

    def __init__(
        self,
        env_id: str,
        *,
        vectorize: str = "sync",
        batch_size: Sequence[int],
        device: str | torch.device = "cpu",
        start_stage: int | None = None,
        actions: Sequence[str] | str | None = None,
        view_doors: bool | None = None,
        no_op_reward: float = 0.0,
        **kwargs: Any,
    ) -> None:
        import_minigrid()
        _check_id(env_id)
        wrapper = functools.partial(
            StagedMiniGrid,
            start_stage=start_stage,
            actions=actions,
            view_doors=view_doors,
            no_op_reward=no_op_reward,
        )
        super().__init__(
            env_id,
            stage_fn=None,  # the wrapper writes "stage"
            vectorize=vectorize,
            wrappers=[wrapper],
            batch_size=batch_size,
            device=device,
            **kwargs,
        )
        self.start_stage = start_stage
