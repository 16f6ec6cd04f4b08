"""MiniGrid's multi-stage levels as tasks: the key, the locked door, then the goal.

`MiniGrid <https://minigrid.farama.org>`_ (Farama's package, the ``minigrid`` extra) has levels
that run through the same three stages: pick up the key (stage 0), open the locked door with it
(stage 1), then reach the goal or pick up the object behind the door (stage 2). Every level of
the DoorKey (``MiniGrid-DoorKey-5x5-v0`` to ``-16x16``), KeyCorridor (``MiniGrid-KeyCorridorS3R1``
to ``S6R3``) and UnlockPickup families is one, chosen by its gymnasium id.

:class:`StagedMiniGrid` (a gymnasium wrapper) supplies what the task needs from the level's
state: the stage (monotone: dropping the key does not undo stage 1), an observation suited to
small networks (:data:`FEATURES`), and episodes that start inside stage k. :class:`MiniGridEnv`
steps its copies as one gymnasium vector env (:class:`~torchrl_stages.GymStageEnv`).
"""

from __future__ import annotations

import functools
from collections import deque
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np
import torch

from torchrl_stages.gym_env import GymStageEnv

__all__ = [
    "ACTIONS",
    "DOORS",
    "FAMILIES",
    "FEATURES",
    "MiniGridEnv",
    "StagedMiniGrid",
    "import_minigrid",
    "level_actions",
    "stage_names",
]

#: the level families with these three stages (the start of their gymnasium ids) and what
#: their last stage heads for
FAMILIES = {
    "MiniGrid-DoorKey-": "goal",
    "MiniGrid-KeyCorridor": "ball",
    "MiniGrid-UnlockPickup-": "box",
}
#: the actions each family's levels can use (MiniGrid's names): ``done`` does nothing in any of
#: them, and ``drop`` is needed only where the key must be put down to pick up the target.
#: An action no level needs still costs exploration: a random walk that carries the key drops
#: it every seventh step on average, and then has to find it again before the door opens
#: (docs/tasks/minigrid.md: on DoorKey-16x16, 1% of 256-step random walks that start with the key
#: open the door with ``drop`` among the actions, 10% without it)
ACTIONS = {
    "MiniGrid-DoorKey-": ("left", "right", "forward", "pickup", "toggle"),
    "MiniGrid-KeyCorridor": ("left", "right", "forward", "pickup", "drop", "toggle"),
    "MiniGrid-UnlockPickup-": ("left", "right", "forward", "pickup", "drop", "toggle"),
}
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
#: the features ``view_doors=True`` appends: which of the cells around the agent are doors
#: (open or closed). In ``blocked_*`` a closed door looks like a wall; KeyCorridor's side rooms
#: are joined to the corridor and to each other by doors, and the key's room is reached
#: through one of them
DOORS = tuple(f"door_{dx}_{dy}" for dy in range(-VIEW, VIEW + 1) for dx in range(-VIEW, VIEW + 1))


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


def stage_names(env_id: str) -> list[str]:
    """The stages of a level: ``["key", "door", <goal, ball or box>]``.

    Examples:
        >>> stage_names("MiniGrid-KeyCorridorS3R3-v0")
        ['key', 'door', 'ball']
    """
    _check_id(env_id)
    return ["key", "door", next(t for f, t in FAMILIES.items() if env_id.startswith(f))]


def level_actions(env_id: str) -> tuple[str, ...]:
    """The actions a level's tasks use by default (:data:`ACTIONS`).

    Examples:
        >>> level_actions("MiniGrid-DoorKey-16x16-v0")
        ('left', 'right', 'forward', 'pickup', 'toggle')
    """
    _check_id(env_id)
    return next(a for f, a in ACTIONS.items() if env_id.startswith(f))


def _check_id(env_id: str) -> None:
    if ":" in env_id or not env_id.startswith(tuple(FAMILIES)):
        raise ValueError(
            f"env_id={env_id!r} is not a MiniGrid level with a key, a locked door and a goal. "
            f"Fix: pick one of the {', '.join(f + '*' for f in FAMILIES)} ids (task=gym takes "
            "any other gymnasium env with a stage function of yours)"
        )


class StagedMiniGrid(gymnasium.Wrapper):
    """A MiniGrid level as a 3-stage task: its stage, features and stage-k starts.

    * **Stages**: 0 until the agent first carries the key, 1 until the locked door is open,
      then 2 (never lower: dropping the key or closing the door keeps the stage).
    * **Observation**: ``{"observation": float32 [len(FEATURES)], "stage": int64 [1]}``: where
      the agent is and faces, what it carries, the door's state, the offsets to the key, the
      door and the target (goal, ball or box), the cell it faces and which of the cells around
      it are blocked. The level's layout varies by seed; the offsets make a policy of them
      carry over between layouts.
    * **Reward**: 1 on success (the level's own, ``1 - 0.9 t / T``, depends on the step count,
      which is not part of the state; each stage's discount makes the policy fast).
    * **Termination**: the level's own, on success only (an evaluation counts every episode
      that terminates as solved). UnlockPickup's box does not open: in the level, toggling it
      replaces it by its (empty) contents, and the level can no longer be solved; here the
      toggle changes nothing. No optimal policy toggles the box, so none changes. Left
      breakable, the episode went on in states that look like those next to the box (its
      offset stays where it was) and are worth nothing: they took the learner of the box
      stage to 0-14% success in 300 000 frames, where a random walk from its starts succeeds
      18% of the time.
    * **Actions**: ``actions`` (MiniGrid's names, e.g. ``("left", "right", "forward")``):
      action ``i`` of the wrapper is ``actions[i]`` of the level; default: the family's
      (:data:`ACTIONS`), every action its levels can need. ``"all"``: the level's seven.
    * **Starts**: ``start_stage=k`` starts inside stage k (the backward schedule's reverse
      curriculum): the level as the seed lays it out, with the key carried (k >= 1) and the
      door open (k = 2), every other door open or closed at random, the agent on a uniformly
      drawn free cell or open doorway it can reach, facing a drawn direction. Stage 0 is drawn
      the same way on levels with rooms behind unlocked doors (KeyCorridor: the level's own start
      is the corridor, the key is in a side room); on DoorKey and UnlockPickup the level's own
      start already is a uniform cell of the key's room, and is kept. ``None``: the level's
      own start.
    * **view_doors**: append :data:`DOORS` to the observation, where the doors around the agent
      are (a closed door is as blocked as a wall).
    * **no_op_reward**: the reward of an action that changes nothing (forward into a wall,
      pickup with nothing to pick up, toggle on a wall; a turn never), 0 by default. At 0 such
      a step is worth ``gamma V(s)``, within ``(1 - gamma) V(s)`` of the best action: small
      Q-value errors make it the greedy one, and a greedy policy that takes it once takes it
      again until the step limit. A negative reward widens that gap by its size, and no
      optimal policy changes: a step that changes nothing is never part of one (it only
      delays the reward). Exploration is untouched (the episode goes on).

    Examples:
        >>> env = StagedMiniGrid(gymnasium.make("MiniGrid-DoorKey-5x5-v0"), start_stage=2)
        >>> obs, _ = env.reset(seed=0)
        >>> int(obs["stage"][0]), obs["observation"].shape == (len(FEATURES),)
        (2, True)
        >>> env.unwrapped.carrying.type, env.door.is_open
        ('key', True)
        >>> env.actions, int(env.action_space.n)
        (('left', 'right', 'forward', 'pickup', 'toggle'), 5)
    """

    num_stages = 3

    def __init__(
        self,
        env: gymnasium.Env,
        start_stage: int | None = None,
        actions: Sequence[str] | str | None = None,
        view_doors: bool = False,
        no_op_reward: float = 0.0,
    ) -> None:
        super().__init__(env)
        level = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        _check_id(level)
        _skip_level_image(env.unwrapped)
        if start_stage is not None and not 0 <= int(start_stage) < self.num_stages:
            raise ValueError(f"start_stage={start_stage}: MiniGrid levels have stages 0, 1, 2")
        self.start_stage = start_stage
        self.actions = _actions(level, actions, env.unwrapped.actions)
        self._level_actions = [int(env.unwrapped.actions[name]) for name in self.actions]
        self.action_space = gymnasium.spaces.Discrete(len(self.actions))
        self.view_doors = bool(view_doors)
        self.no_op_reward = float(no_op_reward)
        #: the names of the observation's features, in order
        self.features = FEATURES + (DOORS if self.view_doors else ())
        self.observation_space = gymnasium.spaces.Dict(
            observation=gymnasium.spaces.Box(-1.0, 1.0, (len(self.features),), np.float32),
            stage=gymnasium.spaces.Box(0, self.num_stages - 1, (1,), np.int64),
        )
        self.stage = 0

    def action(self, name: str) -> int:
        """The wrapper's index of the level's action ``name``."""
        return self.actions.index(name)

    # ------------------------------------------------------------------ the level's objects
    def _objects(self) -> None:
        """Finds the key, the locked door and the target of the level just generated."""
        level = self.env.unwrapped
        self.key = self.door = self.target = None
        self.rooms = False  # doors the agent can open without the key (KeyCorridor's rooms)
        for obj in level.grid.grid:
            if obj is None:
                continue
            if obj.type == "key":
                self.key = obj
            elif obj.type == "door" and obj.is_locked:
                self.door = obj
            elif obj.type == "door":
                self.rooms = True
            elif obj.type == "goal":
                self.target = obj
        if getattr(level, "obj", None) is not None:  # KeyCorridor, UnlockPickup
            self.target = level.obj
        if self.target is not None and self.target.type == "box":
            self.target.toggle = _keep_closed  # (this box; see the class's Termination)

    def _progress(self) -> int:
        level = self.env.unwrapped
        if self.door.is_open and not self.door.is_locked:
            return 2
        return 1 if level.carrying is self.key else 0

    # ------------------------------------------------------------------ starts
    def _reachable(self) -> list[tuple[int, int]]:
        """The cells the agent can stand on and walk to (through doors it can open): free
        cells and open doorways."""
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
        level = self.env.unwrapped
        if stage >= 1:  # the key is carried
            level.grid.set(*self.key.cur_pos, None)
            self.key.cur_pos = np.array([-1, -1])
            level.carrying = self.key
        if stage >= 2:  # the door is open
            self.door.is_locked, self.door.is_open = False, True
        # the other doors (KeyCorridor's rooms) as an earlier stage may have left them: each
        # open or closed; the agent stands on a free cell or in an open doorway (where it is
        # when it has just taken a key from a one-cell room)
        for obj in level.grid.grid:
            if (
                obj is not None
                and obj.type == "door"
                and obj is not self.door
                and not obj.is_locked
            ):
                obj.is_open = bool(self.np_random.integers(2))
        cells = self._reachable()
        level.agent_pos = np.array(cells[int(self.np_random.integers(len(cells)))])
        level.agent_dir = int(self.np_random.integers(4))

    # ------------------------------------------------------------------ observation
    def _features(self) -> np.ndarray:
        level = self.env.unwrapped
        size = float(max(level.width, level.height))
        ax, ay = (int(v) for v in level.agent_pos)

        def offset(obj) -> tuple[float, float]:
            if obj is None or obj.cur_pos is None or obj.cur_pos[0] < 0:  # carried
                return 0.0, 0.0
            return (obj.cur_pos[0] - ax) / size, (obj.cur_pos[1] - ay) / size

        front = level.grid.get(*level.front_pos)
        kinds = np.zeros(7, np.float32)
        if front is None:
            kinds[0] = 1
        elif front.type == "wall":
            kinds[1] = 1
        elif front.type == "door":
            kinds[3 if front.is_open else 2] = 1
        elif front is self.key:
            kinds[4] = 1
        elif front is self.target:
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
        direction = np.eye(4, dtype=np.float32)[level.agent_dir]
        carrying = level.carrying
        return np.array(
            [
                ax / size,
                ay / size,
                *direction,
                float(carrying is self.key),
                float(carrying is not None and carrying is self.target),
                float(self.door.is_open),
                float(self.door.is_locked),
                *offset(self.key),
                *offset(self.door),
                *offset(self.target),
                *kinds,
                *blocked,
                *doors,
            ],
            np.float32,
        )

    def _obs(self) -> dict[str, np.ndarray]:
        return {"observation": self._features(), "stage": np.array([self.stage], np.int64)}

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _, info = self.env.reset(seed=seed, options=options)
        self._objects()
        if self.start_stage is not None and (self.start_stage > 0 or self.rooms):
            self._start_inside(int(self.start_stage))
        self.stage = self._progress()
        return self._obs(), info

    def _state(self) -> tuple:
        """What an action can change: the agent's cell, direction and load, and the cell it
        faces (the object there and its state)."""
        level = self.env.unwrapped
        front = level.grid.get(*level.front_pos)
        door = (
            (front.is_open, front.is_locked) if front is not None and front.type == "door" else ()
        )
        return (
            tuple(int(v) for v in level.agent_pos),
            int(level.agent_dir),
            id(level.carrying),
            id(front),
            door,
        )

    def step(self, action):
        before = self._state() if self.no_op_reward else None
        _, reward, terminated, truncated, info = self.env.step(self._level_actions[int(action)])
        self.stage = max(self.stage, self._progress())
        reward = float(terminated and reward > 0)
        if before is not None and self._state() == before:
            reward += self.no_op_reward  # an action that changed nothing
        return self._obs(), reward, bool(terminated), bool(truncated), info


def _skip_level_image(level: Any) -> None:
    """Stops ``level`` from drawing its own observation, the agent's 7x7 view as an image,
    which this wrapper's features replace: drawing it (rotating and masking the view) was about
    three quarters of a step with 64 copies in a vector env. Its ``gen_obs`` now returns a
    blank image of the same space (what the env checker and the vector env see); the level's
    state, its RNG and every step's result are as before."""
    space = level.observation_space["image"]

    def gen_obs() -> dict[str, Any]:
        image = np.zeros(space.shape, space.dtype)  # new each call, as gymnasium asks
        return {"image": image, "direction": level.agent_dir, "mission": level.mission}

    level.gen_obs = gen_obs


def _keep_closed(env: Any, pos: Any) -> bool:
    """A box's ``toggle`` that leaves it be (MiniGrid's replaces the box by its contents)."""
    return False


def _actions(level: str, actions: Sequence[str] | str | None, enum: Any) -> tuple[str, ...]:
    if actions is None:
        return level_actions(level)
    names = [a.name for a in enum]
    chosen = tuple(names) if actions == "all" else tuple(str(a) for a in actions)
    unknown = [a for a in chosen if a not in names]
    if unknown or not chosen or len(set(chosen)) != len(chosen):
        raise ValueError(
            f"actions={list(chosen)}: not a list of distinct MiniGrid actions. Fix: name some "
            f"of {', '.join(names)} once each (or 'all'; null: {', '.join(level_actions(level))})"
        )
    return chosen


class MiniGridEnv(GymStageEnv):
    """A MiniGrid level (``env_id``) as a batched 3-stage TorchRL env: ``batch_size[0]`` copies
    of :class:`StagedMiniGrid` in a gymnasium vector env.

    Args:
        env_id: a DoorKey, KeyCorridor or UnlockPickup id, e.g. ``"MiniGrid-DoorKey-8x8-v0"``.

    Keyword Args:
        vectorize: ``"sync"`` (default) or ``"async"`` (worker processes).
        batch_size: ``(n,)``: the number of copies.
        device: where the TensorDicts live.
        start_stage: ``None`` (the level's own start) or k: start inside stage k.
        actions: the level's actions the agent uses (:class:`StagedMiniGrid`; ``None``: the
            family's default, :data:`ACTIONS`; ``"all"``: all seven).
        view_doors: append where the doors around the agent are to the observation
            (:data:`DOORS`).
        no_op_reward: the reward of an action that changes nothing (:class:`StagedMiniGrid`).
        **kwargs: the level's own constructor keys (e.g. ``max_steps``).

    Examples:
        >>> env = MiniGridEnv("MiniGrid-DoorKey-5x5-v0", batch_size=(4,), start_stage=1)
        >>> td = env.reset()
        >>> td["stage"].squeeze(-1).tolist(), td["observation"].shape
        ([1, 1, 1, 1], torch.Size([4, 48]))
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
        view_doors: bool = False,
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
