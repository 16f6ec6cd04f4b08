"""A gymnasium env's running episode rebuilt from plain data (generator state, reset seed and
options, actions since), for a resumed run. Imports only numpy and gymnasium: vector env
workers receive :class:`EpisodeReplay` by value."""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
from collections.abc import Mapping
from typing import Any

import gymnasium
import numpy as np

__all__ = ["MAX_REPLAY_STEPS", "EpisodeReplay"]

#: the longest episode whose actions are kept (a longer one cannot be rebuilt on resume)
MAX_REPLAY_STEPS = 100_000
_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64")


def _plain(value: Any) -> Any:
    """``value`` with numpy arrays and scalars as plain lists and numbers (JSON-comparable)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


def _is_plain(value: Any) -> bool:
    if value is None or isinstance(value, bool | int | float | str):
        return True
    if isinstance(value, np.ndarray | np.generic):
        return value.dtype.kind in "biuf"
    if isinstance(value, list | tuple):
        return all(_is_plain(v) for v in value)
    if isinstance(value, Mapping):
        return all(isinstance(k, str) and _is_plain(v) for k, v in value.items())
    return False


def _rng_state(env: gymnasium.Env) -> dict | None:
    generator = getattr(env, "_np_random", None)
    return None if generator is None else _plain(generator.bit_generator.state)


def _set_rng_state(env: gymnasium.Env, state: Mapping) -> None:
    """Puts ``state`` into ``env``'s ``np_random``, keeping its generator object where it can
    (an env may hold a reference to it)."""
    name = state["bit_generator"]
    if name not in _BIT_GENERATORS:
        raise ValueError(f"an unknown bit generator {name!r}")
    generator = getattr(env, "_np_random", None)
    if generator is None or type(generator.bit_generator).__name__ != name:
        generator = np.random.Generator(getattr(np.random, name)())
        env.np_random = generator
    generator.bit_generator.state = dict(state)


def _digest(obs: Any) -> str:
    text = json.dumps(_plain(obs), sort_keys=True, default=repr)
    return hashlib.sha256(text.encode()).hexdigest()


class EpisodeReplay(gymnasium.Wrapper):
    """Keeps what rebuilds the running episode (:meth:`episode_state`); :meth:`rebuild` resets
    and steps the same actions, then checks that the generator and observation end where they
    were (true of an env whose every draw is from ``np_random``).

    Examples:
        >>> env = EpisodeReplay(gymnasium.make("CartPole-v1"))
        >>> _ = env.reset(seed=0)
        >>> for action in (0, 1, 1):
        ...     _ = env.step(action)
        >>> state = env.episode_state()
        >>> twin = EpisodeReplay(gymnasium.make("CartPole-v1"))
        >>> twin.rebuild(state) is None  # the same episode, to the last bit
        True
        >>> bool((twin.unwrapped.state == env.unwrapped.state).all())
        True
    """

    def __init__(self, env: gymnasium.Env) -> None:
        super().__init__(env)
        self.pending_episode: dict | None = None  # a state for rebuild_pending (a vector env's)
        self._start: dict | None = None
        self._actions: list[np.ndarray] = []
        self._obs: Any = None
        self._why_not: str | None = "it was never reset"

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        kept = copy.deepcopy(options) if _is_plain(options) else None
        self._start = {"seed": seed, "rng_start": _rng_state(self.env.unwrapped), "options": kept}
        self._actions, self._why_not = [], None
        if seed is None and self._start["rng_start"] is None:
            self._why_not = "its np_random was never seeded"
        elif seed is not None and not isinstance(seed, int):
            self._why_not = f"its reset seed {seed!r} is no int"
        elif not _is_plain(options):
            self._why_not = "its reset options are not plain data"
        self._obs, info = self.env.reset(seed=seed, options=options)
        return self._obs, info

    def step(self, action: Any):
        out = self.env.step(action)
        if self._why_not is None:
            if len(self._actions) >= MAX_REPLAY_STEPS:
                self._why_not = f"its episode is longer than {MAX_REPLAY_STEPS} steps"
                self._actions = []
            elif isinstance(action, np.ndarray | np.generic | int | float):
                self._actions.append(np.array(action))  # a copy: the caller may reuse its array
            else:
                self._why_not, self._actions = "its actions are not numeric arrays", []
        self._obs = out[0]
        return out

    def episode_state(self) -> dict[str, Any]:
        """What :meth:`rebuild` needs; ``why_not`` says why it cannot rebuild the episode."""
        why_not, rng_now = self._why_not, _rng_state(self.env.unwrapped)
        actions = np.stack(self._actions) if self._actions and why_not is None else None
        if actions is not None and actions.dtype.kind not in "biuf":
            why_not = "its actions are not numeric"
        state = {"why_not": why_not, "rng_now": rng_now}
        if why_not is None:
            state.update(self._start, actions=actions, obs=_digest(self._obs))
        return state

    def rebuild(self, state: Mapping[str, Any]) -> str | None:
        """Rebuilds the episode: ``None``, or why not (the generator then goes on as saved)."""
        try:
            why_not = self._replay(state)
        except Exception as err:  # an env that cannot take its own actions back
            why_not = f"replaying its episode raised {type(err).__name__}: {err}"
        if why_not is not None and state.get("rng_now") is not None:
            # the generator goes on from where it was, for the episodes that start over
            with contextlib.suppress(KeyError, TypeError, ValueError):
                _set_rng_state(self.env.unwrapped, state["rng_now"])
        return why_not

    def rebuild_pending(self) -> str | None:
        """:meth:`rebuild` of :attr:`pending_episode` (set by a vector env's ``set_attr``)."""
        state, self.pending_episode = self.pending_episode, None
        return "no saved episode" if state is None else self.rebuild(state)

    def _replay(self, state: Mapping[str, Any]) -> str | None:
        if state.get("why_not") is not None:
            return str(state["why_not"])
        if state["seed"] is None:
            _set_rng_state(self.env.unwrapped, state["rng_start"])
        options = state["options"]
        self.reset(seed=state["seed"], options=dict(options) if options else options)
        actions = state["actions"]
        for action in () if actions is None else np.asarray(actions):
            self.step(action.copy())
        if _rng_state(self.env.unwrapped) != _plain(state["rng_now"]):
            return "its np_random ends elsewhere than it was"
        if _digest(self._obs) != state["obs"]:
            return "the replayed observation differs from the saved one"
        return None
