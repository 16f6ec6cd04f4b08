"""The stages of a MiniGrid level, from its objects: :class:`LevelPlan` finds the locked door,
its key (and the box it hides in), the ball that blocks the door and the target on a layout;
:func:`probe` checks that every layout of a level has the same stages."""

from __future__ import annotations

import copy
import functools
from collections import deque
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np

__all__ = [
    "MOVES",
    "LevelPlan",
    "UnstageableLevel",
    "probe",
    "refuse",
    "registered_layouts",
    "side",
]

#: the level's actions every staged level needs; ``drop`` joins them where the agent must put
#: down what it carries (to pick up the target or the blocker); ``done`` never does anything
MOVES = ("left", "right", "forward", "pickup", "toggle")
PROBES = 8  # layouts drawn to check that a level's stages are the same on every layout


class UnstageableLevel(ValueError):
    """A level whose objects do not make linear stages; the message says why and what to pick."""


def refuse(level: str, why: str) -> UnstageableLevel:
    """The error for ``level``, which cannot be staged because ``why``, with the fix."""
    return UnstageableLevel(
        f"{level} cannot be staged: {why}. Staging takes one locked door, the one key of its "
        "color (on the floor or in a box; a ball may block the door) and, behind the door, a "
        "goal square or an object to pick up. Fix: pick such a level (DoorKey, KeyCorridor, "
        "UnlockPickup, LockedRoom, ObstructedMaze-1Dl, -1Dlh, -1Dlhb), or task=gym with a "
        "stage function of yours"
    )


@dataclass(frozen=True, eq=False)
class LevelPlan:
    """The objects a layout's stages are about, found from its grid.

    The stages are ``blocker`` (where a ball stands in front of the locked door: put it down
    elsewhere), ``key`` (carry the key, opening the box it hides in), ``door`` (open the locked
    door), then the target's type (``goal``: step on it; an object: pick it up).

    Examples:
        >>> level = gymnasium.make("MiniGrid-ObstructedMaze-1Dlhb-v0").unwrapped
        >>> _ = level.reset(seed=0)
        >>> plan = LevelPlan.of(level)
        >>> plan.stages, plan.box.type, plan.blocker.type, plan.actions[-2:]
        (['blocker', 'key', 'door', 'ball'], 'box', 'ball', ('drop', 'toggle'))
    """

    door: Any
    key: Any
    target: Any
    box: Any = None  # the box the key hides in
    blocker: Any = None  # the object on ``blocked``, the door's cell on the agent's side
    blocked: tuple[int, int] | None = None
    rooms: bool = False  # doors the agent opens without a key

    @property
    def stages(self) -> list[str]:
        """The stage names, in order."""
        return [*(["blocker"] * (self.blocker is not None)), "key", "door", self.target.type]

    @property
    def actions(self) -> tuple[str, ...]:
        """The level's actions the stages need: ``drop`` where something must be put down."""
        drop = self.blocker is not None or self.target.can_pickup()
        return MOVES[:4] + ("drop",) * drop + MOVES[4:]

    @classmethod
    def of(cls, level: Any) -> LevelPlan:
        """The plan of ``level``'s current layout; :class:`UnstageableLevel` if it has none."""
        name = level.spec.id if level.spec is not None else type(level).__name__
        locked, keys, goals, rooms = [], [], [], False
        for i, obj in enumerate(level.grid.grid):
            if obj is None or obj.type == "wall":
                continue
            if obj.cur_pos is None:  # set with grid.set (LockedRoom): where it lies
                obj.cur_pos = np.array([i % level.width, i // level.width])
            if obj.type == "door" and obj.is_locked:
                locked.append(obj)
            elif obj.type == "door":
                rooms = True
            elif obj.type == "key":
                keys.append((obj, None))
            elif obj.type == "box" and getattr(obj.contains, "type", None) == "key":
                keys.append((obj.contains, obj))
            elif obj.type == "goal":
                goals.append(obj)
        if len(locked) != 1:
            raise refuse(name, f"it has {len(locked)} locked doors")
        door = locked[0]
        keys = [(key, box) for key, box in keys if key.color == door.color]
        if len(keys) != 1:
            raise refuse(name, f"it has {len(keys)} keys of its locked door's color")
        key, box = keys[0]
        target = getattr(level, "obj", None)  # the object to pick up (KeyCorridor, ...)
        if not callable(getattr(target, "can_pickup", None)):
            if len(goals) != 1:
                raise refuse(name, f"it has no object to pick up and {len(goals)} goal squares")
            target = goals[0]
        on_side = side(level, door)
        if tuple(target.cur_pos) in on_side:
            raise refuse(name, "its target can be reached without opening the locked door")
        if tuple((key if box is None else box).cur_pos) not in on_side:
            raise refuse(name, "its key lies behind the locked door")
        blocker = blocked = None
        x, y = (int(v) for v in door.cur_pos)
        for cell in ((x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)):
            obj = level.grid.get(*cell) if cell in on_side else None
            movable = obj is not None and obj.can_pickup()
            if movable and all(obj is not other for other in (key, box, target)):
                blocker, blocked = obj, cell
        return cls(door, key, target, box, blocker, blocked, rooms)


def side(level: Any, door: Any) -> set[tuple[int, int]]:
    """The cells the agent reaches without the locked ``door``, moving every object it meets."""
    start = tuple(int(v) for v in level.agent_pos)
    seen, queue = {start}, deque([start])
    while queue:
        x, y = queue.popleft()
        for cell in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
            if cell in seen or not (0 <= cell[0] < level.width and 0 <= cell[1] < level.height):
                continue
            obj = level.grid.get(*cell)
            if obj is None or (obj is not door and obj.type not in ("wall", "lava")):
                seen.add(cell)
                queue.append(cell)
    return seen


def _layouts(level: Any) -> tuple[tuple[str, ...], tuple[str, ...], bool]:
    """The stages, actions and rooms of ``level``'s layouts, the same on the first
    :data:`PROBES` of them (``level`` is reset: pass a copy)."""
    shapes = set()
    for seed in range(PROBES):
        level.reset(seed=seed)
        plan = LevelPlan.of(level)
        shapes.add((tuple(plan.stages), plan.actions, plan.rooms))
    if len(shapes) > 1:
        name = level.spec.id if level.spec is not None else type(level).__name__
        raise refuse(name, f"its layouts differ, with stages {sorted(s[0] for s in shapes)}")
    return shapes.pop()


@functools.cache
def registered_layouts(level_id: str, kwargs: tuple) -> tuple:
    """:func:`_layouts` of the level ``gymnasium.make(level_id, **dict(kwargs))``, once."""
    level = gymnasium.make(level_id, **dict(kwargs)).unwrapped
    try:
        return _layouts(level)
    finally:
        level.close()


def probe(level: Any) -> tuple[tuple[str, ...], tuple[str, ...], bool]:
    """:func:`_layouts` of a level like ``level`` (once per id and keywords), which it leaves be."""
    from minigrid.minigrid_env import MiniGridEnv as Level

    if not isinstance(level, Level):
        raise UnstageableLevel(
            f"{type(level).__name__} is not a MiniGrid level. Fix: pick a MiniGrid level id, "
            "or task=gym with a stage function of yours"
        )
    key = None if level.spec is None else tuple(sorted(level.spec.kwargs.items()))
    try:
        hash(key)
    except TypeError:  # keywords that cannot be a cache key
        key = None
    if key is None:
        return _layouts(copy.deepcopy(level))
    return registered_layouts(level.spec.id, key)
