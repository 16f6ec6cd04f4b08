"""Gymnasium envs as multi-stage tasks (``task=gym``): a stage function over a vector env."""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import cloudpickle
import gymnasium
import numpy as np
import torch
from hydra.utils import get_method
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite
from torchrl.envs import GymWrapper
from torchrl.envs.gym_like import BaseInfoDictReader

from torchrl_stages import episode_replay
from torchrl_stages.episode_replay import EpisodeReplay
from torchrl_stages.transforms import SUCCESS_KEY, StageFn

__all__ = ["GymStageEnv", "SuccessKeyError", "SuccessReader", "threshold_stage"]

log = logging.getLogger("torchrl_stages")
# env ids whose resume was warned about: once for all the envs of an id
_WARNED: set[str] = set()
# the async workers get EpisodeReplay by value: they need not import this package (seconds each)
cloudpickle.register_pickle_by_value(episode_replay)


def threshold_stage(
    td: TensorDictBase,
    *,
    thresholds: Sequence[float],
    key: NestedKey = "observation",
    index: int = 0,
) -> torch.Tensor:
    """A stage function: how many ``thresholds`` lie at or below ``td[key][..., index]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict(observation=torch.tensor([[0.1], [0.5], [0.9]]), batch_size=[3])
        >>> threshold_stage(td, thresholds=[0.5, 0.8]).squeeze(-1)
        tensor([0, 1, 2])
    """
    value = td.get(key)[..., index : index + 1]
    edges = torch.as_tensor(list(thresholds), dtype=value.dtype, device=value.device)
    return (value >= edges).sum(-1, keepdim=True).long()


def _stage_function(stage_fn: StageFn | str) -> StageFn:
    fn = get_method(stage_fn) if isinstance(stage_fn, str) else stage_fn
    if not callable(fn):
        raise TypeError(
            f"stage_fn must be a function of the tensordict, got {stage_fn!r}. Fix: set "
            "task.env.stage_fn._target_=my_module.my_stage_fn (with _partial_: true)"
        )

    @functools.wraps(fn)
    def stage(td: TensorDictBase) -> torch.Tensor:
        out = torch.as_tensor(fn(td), device=td.device).long()
        return out.unsqueeze(-1) if out.shape == td.batch_size else out

    return stage


class SuccessKeyError(ValueError):
    """The env's ``info`` never carried the success key."""


class SuccessReader(BaseInfoDictReader):
    """Reads a gymnasium env's success flag ``info[info_key]`` (``False`` where absent) into the
    ``"success"`` entry; :class:`SuccessKeyError` after ``patience`` ended episodes without it.

    Examples:
        >>> from tensordict import TensorDict
        >>> reader = SuccessReader("is_success", batch_size=(2,))
        >>> td = reader({"is_success": np.array([True, False])}, TensorDict(batch_size=[2]))
        >>> td["success"].squeeze(-1).tolist()
        [True, False]
    """

    def __init__(
        self,
        info_key: str,
        *,
        batch_size: Sequence[int],
        device: str | torch.device = "cpu",
        patience: int = 100,
    ) -> None:
        self.info_key, self.patience = info_key, patience
        self._ended, self._seen = 0, False  # episodes ended before the key was first reported
        self._spec = Composite(
            {SUCCESS_KEY: Categorical(2, shape=(*batch_size, 1), dtype=torch.bool, device=device)},
            shape=tuple(batch_size),
            device=device,
        )

    @property
    def info_spec(self) -> Composite:
        return self._spec

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        value = info_dict.get(self.info_key)
        self._seen |= value is not None
        done = None if self._seen else tensordict.get("done", None)  # a step's (a reset has none)
        if done is not None:
            self._ended += int(done.sum())
            if self._ended >= self.patience:
                raise SuccessKeyError(
                    f"task.env.success_key={self.info_key!r}: {self._ended} episodes of the env "
                    f"ended and none reported info[{self.info_key!r}], so every episode would "
                    "count as failed. Fix: set task.env.success_key to the key the env's `info` "
                    "carries on every episode's last step, or null to count terminations as "
                    "successes"
                )
        flag = np.zeros(tensordict.batch_size, bool) if value is None else np.asarray(value)
        flag = torch.as_tensor(flag.astype(bool)).reshape(*tensordict.batch_size, 1)
        return tensordict.set(SUCCESS_KEY, flag.to(tensordict.device))


class GymStageEnv(GymWrapper):
    """A gymnasium env as a multi-stage task: ``batch_size[0]`` copies stepped as one vector env.

    A copy resets only when torchrl asks, and ``state_dict`` holds the copies' running episodes
    (:class:`~torchrl_stages.episode_replay.EpisodeReplay`), so a resumed run goes on bitwise
    where the env draws only from its ``np_random``. ``env_id`` ``"module:Id"`` imports
    ``module`` first; ``success_key``: the ``info`` flag (``None``: solved when terminated).

    Examples:
        >>> lean = functools.partial(threshold_stage, thresholds=[0.0], index=2)  # left, then right
        >>> env = GymStageEnv("CartPole-v1", lean, num_stages=2, batch_size=(4,))
        >>> env.rollout(3, break_when_any_done=False)["observation"].shape, env.max_steps
        (torch.Size([4, 3, 4]), 500)
        >>> env.close()
    """

    def __init__(
        self,
        env_id: str,
        stage_fn: StageFn | str | None,
        num_stages: int | None = None,
        *,
        success_key: str | None = None,
        vectorize: str = "sync",
        wrappers: Sequence[Callable[[gymnasium.Env], gymnasium.Env]] = (),
        batch_size: Sequence[int],
        device: str | torch.device = "cpu",
        **kwargs: Any,
    ) -> None:
        batch = tuple(int(b) for b in batch_size)
        if len(batch) != 1:
            raise ValueError(f"GymStageEnv needs batch_size=(n,), got {batch}")
        if vectorize not in ("sync", "async"):
            raise ValueError(
                f"vectorize={vectorize!r}: Fix: task.env.vectorize=sync (copies stepped in "
                "this process) or async (worker processes)"
            )
        # torchrl's GymWrapper metaclass adds this key to every constructor call
        native = kwargs.pop("_torchrl_native_autoreset_requested", False)
        made = gymnasium.make(env_id, **kwargs)
        for wrap in wrappers:
            made = wrap(made)
        with made:  # closed once read
            found = getattr(made, "num_stages", None)
            if found is None:
                found = getattr(made.unwrapped, "num_stages", None)
            max_steps = made.spec.max_episode_steps if made.spec is not None else None
            if max_steps is None:  # an env that truncates its episodes itself (MiniGrid)
                max_steps = getattr(made.unwrapped, "max_steps", None)
        if num_stages is None and found is None:
            raise ValueError(
                f"the gymnasium env {env_id!r} has no num_stages attribute. Fix: set "
                "task.env.num_stages"
            )
        vector = gymnasium.make_vec(
            env_id,
            num_envs=batch[0],
            vectorization_mode=vectorize,
            vector_kwargs={"autoreset_mode": gymnasium.vector.AutoresetMode.DISABLED},
            wrappers=[*wrappers, EpisodeReplay],
            **kwargs,
        )
        super().__init__(
            vector,
            categorical_action_encoding=True,
            device=device,
            _torchrl_native_autoreset_requested=native,
        )
        self._success_reader = None
        if success_key is not None:
            self._success_reader = SuccessReader(
                str(success_key), batch_size=batch, device=self.device
            )
            self.set_info_dict_reader(self._success_reader)
        self.env_id = env_id
        _WARNED.discard(env_id)
        self.num_stages = int(num_stages if num_stages is not None else found)
        self.stage_fn = None if stage_fn is None else _stage_function(stage_fn)
        if max_steps is not None:  # else evaluations cap episodes at 1000 steps
            self.max_steps = int(max_steps)
        self.episodes_rebuilt = True  # False after a load_state_dict that could not rebuild them

    def load_state_dict(
        self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False
    ) -> Any:
        if "_extra_state" not in state_dict:
            state_dict = {**state_dict, "_extra_state": {}}
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def get_extra_state(self) -> dict[str, Any]:
        if self.is_closed:
            return {}
        reader = self._success_reader
        return {
            "copies": list(self._env.call("episode_state")),
            "success_reader": None if reader is None else [reader._ended, reader._seen],
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        copies, num, fix = state.get("copies"), self.batch_size[0], ""
        if copies is None or len(copies) != num:
            held = "none of its episodes" if copies is None else f"{len(copies)} copies for {num}"
            failures = [(0, f"the checkpoint holds {held}")]
        else:
            self._env.set_attr("pending_episode", list(copies))
            failures = [(i, why) for i, why in enumerate(self._env.call("rebuild_pending")) if why]
            fix = " Fix: draw every random number of the env from its self.np_random"
        reader, saved = self._success_reader, state.get("success_reader")
        if reader is not None and saved is not None:
            reader._ended, reader._seen = int(saved[0]), bool(saved[1])
        self.episodes_rebuilt = not failures
        if failures and self.env_id not in _WARNED:
            _WARNED.add(self.env_id)
            index, why = failures[0]
            log.warning(
                f"resume: the gymnasium env {self.env_id!r} did not rebuild its running episodes "
                f"({len(failures)} of {num} copies; copy {index}: {why}): they start over, so "
                f"this run is not bitwise equal to an uninterrupted one.{fix} "
                "(docs/guides/bring-your-own-env.md, Resume)"
            )
