"""Gymnasium envs as multi-stage tasks: a batched TorchRL env named by its id and stage function.

``task=gym`` builds :class:`GymStageEnv` from ``task.env``: the gymnasium env id (``module:Id``
imports ``module`` first, where it registers the env), the stage function (``stage_fn``) and
the env's own constructor keys. Everything the task protocol needs (a batch dimension, the
device, ``num_stages``, ``stage_fn``, ``start_stage`` for envs that can start inside a stage) is
added here, so a config names only the env and its stage function.
"""

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
from torchrl_stages.transforms import SUCCESS_KEY

__all__ = ["GymStageEnv", "SuccessKeyError", "SuccessReader", "threshold_stage"]

StageFn = Callable[[TensorDictBase], torch.Tensor]
_UNSET = object()
log = logging.getLogger("torchrl_stages")
#: env ids whose episodes could not be rebuilt since an env of that id was last built: a resume
#: that loads a training and an evaluation env warns once
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
    """A stage function: the number of ``thresholds`` at or below ``td[key][..., index]``
    (``len(thresholds) + 1`` stages). Name it in a config with ``_partial_: true``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> td = TensorDict(observation=torch.tensor([[0.1], [0.5], [0.9]]), batch_size=[3])
        >>> threshold_stage(td, thresholds=[0.5, 0.8]).squeeze(-1)
        tensor([0, 1, 2])
    """
    value = td.get(key)[..., index : index + 1]
    edges = torch.as_tensor(list(thresholds), dtype=value.dtype, device=value.device)
    return (value >= edges).sum(-1, keepdim=True).long()


def _stage_function(stage_fn: StageFn | str) -> StageFn:
    """The stage function from a callable (e.g. a ``_partial_: true`` node) or a dotted path,
    returning int64 ``[*batch, 1]``."""
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


VECTORIZE = ("sync", "async")


class SuccessKeyError(ValueError):
    """The env's ``info`` has never carried the success key on an episode's last step."""


class SuccessReader(BaseInfoDictReader):
    """Reads a gymnasium env's success flag, ``info[info_key]`` (``"is_success"`` in
    gymnasium-robotics and Stable-Baselines3), into a boolean ``"success"`` entry ``[n, 1]``:
    the entry evaluations count an episode's success by (see
    :func:`torchrl_stages.evaluate.ended_well`). The env must report it at least on the last
    step of every episode; a copy that does not report it on a step reads ``False``. Once
    ``patience`` episodes have ended with the key never reported, :class:`SuccessKeyError`
    stops the run (a misspelled key would count every episode as failed).

    Examples:
        >>> import numpy as np
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
        self.info_key = info_key
        self.patience = patience
        self._ended = 0  # episodes ended (the env's own done) while the key was never reported
        self._seen = False
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
        if value is None:
            done = tensordict.get("done", None)  # a step's (a reset has none)
            if not self._seen and done is not None:
                self._ended += int(done.sum())
                if self._ended >= self.patience:
                    raise SuccessKeyError(
                        f"task.env.success_key={self.info_key!r}: {self._ended} episodes of "
                        f"the env ended and none reported info[{self.info_key!r}], so every "
                        "episode would count as failed. Fix: set task.env.success_key to the "
                        "key the env's `info` carries on every episode's last step, or null to "
                        "count terminations as successes"
                    )
            flag = torch.zeros(tensordict.batch_size, dtype=torch.bool)
        else:
            self._seen = True
            flag = torch.as_tensor(np.asarray(value).astype(bool))
        flag = flag.reshape(*tensordict.batch_size, 1).to(tensordict.device)
        tensordict.set(SUCCESS_KEY, flag)
        return tensordict


class GymStageEnv(GymWrapper):
    """A gymnasium env as a multi-stage task: ``batch_size[0]`` copies stepped as one gymnasium
    vector env (``SyncVectorEnv``, or ``AsyncVectorEnv`` worker processes), wrapped by torchrl's
    ``GymWrapper``, with what a multi-stage task needs: ``num_stages`` and ``stage_fn``.

    The vector env runs with ``autoreset_mode=DISABLED``: a copy resets only when torchrl asks
    (``"_reset"``), so a copy that ends its episode (or leaves a stage) restarts where the task
    says, inside stage k for stage-k starts.

    Each copy is wrapped in :class:`~torchrl_stages.episode_replay.EpisodeReplay` (outermost),
    so ``state_dict`` holds the copies' running episodes as plain data and ``load_state_dict``
    rebuilds them: a resumed run goes on bitwise on an env whose random draws all come from
    its ``np_random`` (otherwise :attr:`episodes_rebuilt` is ``False`` and one warning says the
    episodes start over).

    Args:
        env_id: the gymnasium id; ``"my_module:MyEnv-v0"`` imports ``my_module`` first.
        stage_fn: ``stage_fn(td) -> int64 [*batch, 1]``, the stage of each state (a callable or
            a dotted path); ``None`` when the env writes a ``"stage"`` observation itself.
        num_stages: the number of stages (default: the gymnasium env's ``num_stages``).

    Keyword Args:
        success_key: the ``info`` key of the env's success flag (e.g. ``"is_success"``), read
            into a boolean ``"success"`` entry (:class:`SuccessReader`): evaluations count an
            episode as solved when it is true on the episode's last step. ``None`` (default):
            an episode is solved when it terminates (for envs that terminate only on success).
        vectorize: ``"sync"`` (default: the copies step one after another in this process) or
            ``"async"`` (one worker process per copy: for envs whose step costs more than the
            inter-process round trip, about 0.1 ms).
        wrappers: gymnasium wrapper factories applied to each copy, in order.
        batch_size: ``(n,)``: the number of env copies.
        device: where the TensorDicts live.
        start_stage: given (``None`` included) only for tasks with ``task.stage_starts=true``;
            passed to the gymnasium env's constructor, which then starts its episodes inside
            that stage (``None``: the task's own starts).
        **kwargs: the gymnasium env's own constructor keys.

    Attributes:
        max_steps: the env's ``max_episode_steps`` (else its ``max_steps`` attribute): the
            evaluations' episode cap, when it has one.
        episodes_rebuilt: whether the last ``load_state_dict`` rebuilt every copy's episode.

    Examples:
        >>> env = GymStageEnv(
        ...     "CartPole-v1",
        ...     stage_fn=functools.partial(threshold_stage, thresholds=[0.0], index=2),
        ...     num_stages=2,  # the pole leans left, then right
        ...     batch_size=(4,),
        ... )
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
        start_stage: Any = _UNSET,
        **kwargs: Any,
    ) -> None:
        batch = tuple(int(b) for b in batch_size)
        if len(batch) != 1:
            raise ValueError(f"GymStageEnv needs batch_size=(n,), got {batch}")
        if vectorize not in VECTORIZE:
            raise ValueError(
                f"vectorize={vectorize!r}: Fix: task.env.vectorize=sync (copies stepped in "
                "this process) or async (worker processes)"
            )
        # torchrl's GymWrapper metaclass adds this key to every constructor call
        native = kwargs.pop("_torchrl_native_autoreset_requested", False)
        if start_stage is not _UNSET:
            kwargs["start_stage"] = start_stage
        made = gymnasium.make(env_id, **kwargs)
        for wrap in wrappers:
            made = wrap(made)
        try:
            found = getattr(made, "num_stages", None)
            if found is None:
                found = getattr(made.unwrapped, "num_stages", None)
            max_steps = made.spec.max_episode_steps if made.spec is not None else None
            if max_steps is None:  # an env that truncates its episodes itself (MiniGrid)
                max_steps = getattr(made.unwrapped, "max_steps", None)
        finally:
            made.close()
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
        if success_key is not None:
            self.set_info_dict_reader(
                SuccessReader(str(success_key), batch_size=batch, device=self.device)
            )
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
        """``nn.Module``'s, where a state without the copies' episodes (a checkpoint written
        before they were kept) warns and starts them over instead of failing."""
        if "_extra_state" not in state_dict:
            state_dict = {**state_dict, "_extra_state": {}}
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def get_extra_state(self) -> dict[str, Any]:
        """The running episodes of the copies (:meth:`EpisodeReplay.episode_state`, plain data
        and arrays) and the success reader's count: what a resumed run continues from."""
        if self.is_closed:
            return {}
        reader = next((r for r in self.info_dict_reader if isinstance(r, SuccessReader)), None)
        return {
            "env_id": self.env_id,
            "copies": list(self._env.call("episode_state")),
            "success_reader": None if reader is None else [reader._ended, reader._seen],
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        """Rebuilds the copies' saved episodes (:meth:`EpisodeReplay.rebuild`). An env whose
        episodes do not come back as they were (draws from elsewhere than ``np_random``) sets
        :attr:`episodes_rebuilt` to ``False`` (the collector then starts its episodes over)
        and logs one warning line (once for the envs of one id loaded after they were built)."""
        copies = state.get("copies")
        num = self.batch_size[0]
        fix = ""
        if copies is None:
            failures = [(0, "the checkpoint holds none of its episodes")]
        elif len(copies) != num:
            failures = [(0, f"the checkpoint holds {len(copies)} copies for {num}")]
        else:
            self._env.set_attr("pending_episode", list(copies))
            failures = [(i, why) for i, why in enumerate(self._env.call("rebuild_pending")) if why]
            fix = " Fix: draw every random number of the env from its self.np_random"
        reader = next((r for r in self.info_dict_reader if isinstance(r, SuccessReader)), None)
        if reader is not None and state.get("success_reader") is not None:
            reader._ended, reader._seen = (
                int(state["success_reader"][0]),
                bool(state["success_reader"][1]),
            )
        self.episodes_rebuilt = not failures
        if failures and self.env_id not in _WARNED:
            _WARNED.add(self.env_id)
            index, why = failures[0]
            log.warning(
                "resume: the gymnasium env %r did not rebuild its running episodes (%d of %d "
                "copies; copy %d: %s): they start over, so this run is not bitwise equal to an "
                "uninterrupted one.%s (docs/guides/bring-your-own-env.md, Resume)",
                self.env_id,
                len(failures),
                num,
                index,
                why,
                fix,
            )
