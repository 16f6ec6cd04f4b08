"""The one training loop of one stage, shared by every algorithm."""

from __future__ import annotations

import copy
import functools
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.evaluate import discounted_return, evaluate_policy
from torchrl_stages.learners import Learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.preemption import Interrupted, requested
from torchrl_stages.replay import stage_replay_buffer
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import NonFiniteInputError, NonFiniteValueError


class EnvError(RuntimeError):
    """The env returned a NaN or infinite observation or reward: the env's fault, not the
    learner's. The message names the entry and the stage.

    Attributes:
        stage: the stage whose training found it.
        key: the env's entry that is not finite.
    """

    def __init__(self, stage: int, name: str, key: NestedKey, cause: str = "") -> None:
        where = f" ({cause})" if cause else ""
        super().__init__(
            f"stage {stage} ({name}): the env returned a non-finite {key!r}{where}. Nothing "
            f"of stage {stage} was saved. Fix: the env's step/reset must return finite "
            "observations and rewards (check it with torchrl's check_env_specs and a rollout)"
        )
        self.stage, self.key = stage, key


def non_finite_entries(td: TensorDictBase, skip: Sequence[NestedKey] = ()) -> list[NestedKey]:
    """The floating-point entries of ``td`` holding a NaN or an infinity (``skip`` aside).

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict(obs=torch.tensor([[0.0, float("nan")]]), action=torch.ones(1, 1),
        ...                 batch_size=[1])
        >>> non_finite_entries(td)
        ['obs']
    """
    skip_keys = {(k,) if isinstance(k, str) else tuple(k) for k in skip}
    found = []
    for key, value in td.items(True, True):
        tup = (key,) if isinstance(key, str) else tuple(key)
        if tup in skip_keys or tup[-1:] in skip_keys or not value.is_floating_point():
            continue
        if not bool(torch.isfinite(value).all()):
            found.append(key)
    return found


def stage_failure(
    err: FloatingPointError, stage: int, name: str, learner: Learner, buffer: ReplayBuffer
) -> RuntimeError:
    """The error a non-finite loss, gradient or value becomes: :class:`EnvError` when the
    env's own data (the transitions in the stage's ``buffer``, its actions aside) holds the NaN
    or infinity, else :class:`DivergenceError`."""
    if isinstance(err, NonFiniteInputError):
        return EnvError(stage, name, err.key, "the next stage's value of it is not finite")
    stored = buffer.storage[: len(buffer)] if len(buffer) else None
    bad = non_finite_entries(stored, skip=[learner.specs.action_key]) if stored is not None else []
    if bad:
        return EnvError(stage, name, bad[0], f"found in the replay buffer after: {err}")
    return DivergenceError(stage, name, learner, err)


class DivergenceError(RuntimeError):
    """A stage's training produced a NaN or infinite loss, gradient or parameter, or got a
    non-finite transition value from the next stage.

    The message names the stage, its algorithm, what was not finite and where; nothing of the
    stage has been saved.
    """

    def __init__(self, stage: int, name: str, learner: Learner, cause: FloatingPointError) -> None:
        key = f"task.stages.{name}"
        rates = " or ".join(f"{key}.{k}" for k in learner.lr_keys)
        super().__init__(
            f"stage {stage} ({name}, {learner.algo}) diverged: {cause}. Nothing of stage "
            f"{stage} was saved. Fix: lower {rates}, or set {key}.max_grad_norm"
        )
        self.stage = stage


@dataclass
class StageResult:
    """What training one stage did."""

    stage: int
    frames: int
    updates: int
    seconds: float
    success_rate: float | None  # last greedy stage evaluation (None: never evaluated)
    value_error: float | None  # mean |V(s_0) - greedy discounted return| at that evaluation
    early_stopped: bool
    restored_best: bool = False  # budget ran out; the best evaluated weights were restored
    # wall-clock seconds per phase: collect, sample, update, evaluate, log
    timing: dict[str, float] = field(default_factory=dict)
    # mean discounted return of the greedy episodes at that evaluation: the stage's objective
    # (the joint schedule: that of the whole-task episodes of its last phase, for every stage)
    discounted_return: float | None = None


def progress_bar(initial: int, total: int, desc: str, enabled: bool) -> tqdm:
    """A stage's (or joint phase's) frame bar, shown only on a terminal."""
    return tqdm(
        initial=initial,
        total=total,
        desc=desc,
        unit="frame",
        disable=not (enabled and sys.stderr.isatty()),
        leave=False,
    )


def first_evaluation(cfg: StageConfig) -> int:
    """Frames of a stage's first evaluation: ``eval_every``, or, with an early stop that the
    budget allows, the first of the ``patience`` evaluations that can stop the stage at
    ``min_frames`` (earlier ones could not stop it: evaluations only as often as the early stop
    needs)."""
    first = int(cfg.eval_every)
    if cfg.success_threshold is not None and int(cfg.min_frames) <= int(cfg.frames):
        first = max(first, int(cfg.min_frames) - (int(cfg.patience) - 1) * first)
    return first


class Stopwatch:
    """Wall-clock seconds spent in named phases of a loop.

    Examples:
        >>> watch = Stopwatch()
        >>> with watch("update"):
        ...     pass
        >>> list(watch.seconds)
        ['update']
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - start

    def timed(self, phase: str, iterable):
        """Yields from ``iterable``, timing each ``next`` as ``phase``."""
        iterator = iter(iterable)
        while True:
            with self(phase):
                item = next(iterator, _END)
            if item is _END:
                return
            yield item


_END = object()


def checkpoint_or_stop(
    checkpoints: StageCheckpoints | None,
    frames: int,
    state: dict,
    before_save: Callable[[], None],
    where: str,
    watch: Stopwatch,
) -> None:
    """The end of a loop's iteration: writes a checkpoint when one is due or a stop was asked
    for (:mod:`torchrl_stages.preemption`), then raises :class:`Interrupted` in the latter case
    (``before_save`` updates what the checkpoint records of the loop)."""
    signum = requested()
    if checkpoints is not None and (checkpoints.due(frames) or signum is not None):
        with watch("checkpoint"):
            before_save()
            checkpoints.save(frames, state)
    if signum is not None:
        raise Interrupted(signum, f"{where} at {frames} frames")


class _EvalMonitor:
    """Early stop and best-weights bookkeeping over a stage's greedy evaluations.

    The early-stop criterion must hold for ``patience`` consecutive evaluations after
    ``min_frames``. When the budget runs out first, :meth:`restore_best` puts back the weights of
    the best evaluation, if ``keep_best``: highest success, then lowest value error (``keep_best_by
    = "value_error"``) or highest mean discounted return (``"return"``).
    """

    def __init__(self, cfg: StageConfig) -> None:
        self.cfg = cfg
        self.streak = 0
        self.stopped = False
        self.best: tuple[float, float] | None = None  # (success, value error) of the best
        self.best_score: tuple[float, float] | None = None
        self.best_is_last = False
        self.best_state: dict | None = None
        self.last: tuple[float, float] | None = None
        self.best_return: float | None = None  # mean discounted return of those evaluations
        self.last_return: float | None = None

    def record(
        self,
        learner: Learner,
        success: float,
        value_error: float,
        frames: int,
        ret: float | None = None,
    ) -> bool:
        """Records one evaluation (``ret``: its mean discounted return); returns whether the
        stage should stop now."""
        cfg = self.cfg
        self.last, self.last_return = (success, value_error), ret
        by_return = 0.0 if ret is None else ret
        score = (success, by_return if cfg.keep_best_by == "return" else -value_error)
        self.best_is_last = cfg.keep_best and (self.best_score is None or score > self.best_score)
        if self.best_is_last:
            self.best_score, self.best = score, (success, value_error)
            self.best_return = ret
            self.best_state = copy.deepcopy(learner.state_dict())
        met = (
            cfg.success_threshold is not None
            and success >= cfg.success_threshold
            and (cfg.value_tolerance is None or value_error <= cfg.value_tolerance)
        )
        self.streak = self.streak + 1 if met else 0
        self.stopped = self.streak >= cfg.patience and frames >= cfg.min_frames
        return self.stopped

    _FIELDS = (
        "streak",
        "stopped",
        "best",
        "best_score",
        "best_is_last",
        "last",
        "best_return",
        "last_return",
    )

    def state_dict(self) -> dict:
        return {**{f: getattr(self, f) for f in self._FIELDS}, "best_state": self.best_state}

    def load_state_dict(self, state: dict) -> None:
        for f in self._FIELDS:
            # checkpoints from before the returns were kept lack those two fields
            value = state.get(f) if f.endswith("_return") else state[f]
            setattr(self, f, tuple(value) if isinstance(value, list) else value)
        self.best_state = state["best_state"]

    def restore_best(self, learner: nn.Module) -> bool:
        """Puts back the best evaluated weights (the budget ran out before the early stop);
        returns whether they differ from the weights the loop ended with (updates may follow
        the last evaluation)."""
        if self.stopped or self.best_state is None:
            return False
        current = learner.state_dict()
        changed = any(not torch.equal(current[k], v) for k, v in self.best_state.items())
        if changed:
            learner.load_state_dict(self.best_state)
        return changed

    @property
    def final(self) -> tuple[float | None, float | None]:
        """Evaluation of the weights the stage ends with."""
        if self.last is None:
            return None, None
        if self.stopped or self.best is None:
            return self.last
        return self.best  # restore_best puts these weights back

    @property
    def final_return(self) -> float | None:
        """Mean discounted return of the evaluation :attr:`final` reports."""
        if self.stopped or self.best is None:
            return self.last_return
        return self.best_return


class StageTrainer:
    """Trains stage ``stage``: collector -> replay buffer -> learner updates -> evaluation.

    ``env`` is the stage's training env (starts inside the stage, transitions terminal, rewards
    rewritten by :class:`~torchrl_stages.transforms.StageTransform`); ``eval_env`` is the same
    kind of env used for greedy evaluations and the early stop on ``cfg.success_threshold``.
    With ``checkpoints`` the loop saves a checkpoint every ``checkpoints.every`` frames and
    starts from the newest one on disk, so that an interrupted stage goes on exactly where it
    stopped (the logger's files are rewound with it when it has ``position``/``rewind``).
    ``gammas`` (one per stage) makes evaluations compare values with the stage-discounted
    return; ``postproc`` transforms each collected batch and ``extra_keys`` are stored with
    what the loss reads (the flat schedule's per-transition discounts); ``on_evaluate(frames)``
    runs after every evaluation.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
        >>> from torchrl_stages.task import StagedTask
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": {"gamma": 0.9}, "b": {"gamma": 0.9}},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> cfg = OmegaConf.structured(DQNConfig(frames=512, frames_per_batch=64, num_envs=8,
        ...                                      init_random_frames=64, eval_every=0))
        >>> learner = DQNLearner(cfg, task.specs(1))
        >>> trainer = StageTrainer(1, learner, task.stage_env(1, 8), task.stage_env(1, 8), cfg)
        >>> trainer.train().frames
        512
    """

    def __init__(
        self,
        stage: int,
        learner: Learner,
        env: EnvBase,
        eval_env: EnvBase,
        cfg: StageConfig,
        *,
        logger: Logger | None = None,
        progress: bool = False,
        name: str | None = None,
        checkpoints: StageCheckpoints | None = None,
        gammas: Sequence[float] | None = None,
        postproc: Callable[[TensorDictBase], TensorDictBase] | None = None,
        extra_keys: Sequence[NestedKey] = (),
        on_evaluate: Callable[[int], None] | None = None,
    ) -> None:
        self.on_evaluate = on_evaluate
        self.gammas = gammas
        self.postproc = postproc
        self.keys = list(dict.fromkeys([*learner.replay_keys, *extra_keys]))
        self.stage = stage
        self.learner = learner
        self.env = env
        self.eval_env = eval_env
        self.cfg = cfg
        self.logger = logger
        self.progress = progress
        self.name = name or str(stage)
        self.prefix = f"train/stage_{stage}"
        self.checkpoints = checkpoints

    def train(self) -> StageResult:
        cfg, learner = self.cfg, self.learner
        collector = StageCollector(
            self.env,
            learner.exploration_policy,
            frames_per_batch=cfg.frames_per_batch,
            total_frames=cfg.frames,
            init_random_frames=cfg.init_random_frames,
        )
        # one draw for all of a batch's gradient steps, split per step: on CPU the same indices
        # as a draw per step (the sampler's randint stream is the same) unless the update itself
        # draws random numbers in between (TD3's target smoothing); one storage read, not n
        steps = int(cfg.updates_per_batch)
        draws, per_draw = (steps, 1) if learner.update_draws_random else (min(steps, 1), steps)
        buffer = stage_replay_buffer(cfg.buffer_size, learner.device)
        monitor = _EvalMonitor(cfg)
        counters = {"next_eval": first_evaluation(cfg), "seconds": 0.0, "log": {}}
        state = {  # what a checkpoint holds (and the process-global generators)
            "learner": StateOf(learner.checkpoint, learner.load_checkpoint),
            "replay_buffer": buffer,
            "collector": collector,
            "eval_env": getattr(self.eval_env, "base_env", self.eval_env),
            "monitor": monitor,
            "counters": counters,
        }
        if self.checkpoints is not None and (latest := self.checkpoints.latest()) is not None:
            self.checkpoints.load(latest, state)
            self._rewind_log(counters["log"])
        start = time.perf_counter() - counters["seconds"]
        watch = Stopwatch()
        bar = progress_bar(
            collector.frames, int(cfg.frames), f"stage {self.stage} ({self.name})", self.progress
        )
        try:
            for batch in watch.timed("collect", collector):
                frames = collector.frames
                keep_threads()
                with watch("collect"):
                    if self.postproc is not None:
                        batch = self.postproc(batch)
                    buffer.extend(batch.reshape(-1).select(*self.keys, strict=False))
                learner.anneal(frames)
                losses = []
                if frames >= cfg.init_random_frames:
                    for _ in range(draws):
                        with watch("sample"):
                            drawn = buffer.sample(cfg.batch_size * per_draw)
                            samples = drawn.split(cfg.batch_size)
                        for sample in samples:
                            with watch("update"):
                                keep_threads()
                                losses.append(learner.update(sample))
                    learner.check_finite()
                with watch("log"):
                    self._log_batch(batch, losses, frames)
                bar.update(batch.numel())
                stop = False
                if cfg.eval_every > 0 and frames >= counters["next_eval"]:
                    counters["next_eval"] += cfg.eval_every
                    with watch("evaluate"):
                        success, value_error, ret = self.evaluate(frames)
                        if self.on_evaluate is not None:
                            self.on_evaluate(frames)
                    bar.set_postfix(success=f"{success:.2f}", value_error=f"{value_error:.3f}")
                    stop = monitor.record(learner, success, value_error, frames, ret)
                if stop:
                    break
                checkpoint_or_stop(
                    self.checkpoints,
                    frames,
                    state,
                    lambda: counters.update(
                        seconds=time.perf_counter() - start, log=self._log_position()
                    ),
                    f"stage {self.stage} ({self.name})",
                    watch,
                )
        except (NonFiniteError, NonFiniteValueError) as err:
            raise stage_failure(err, self.stage, self.name, learner, buffer) from err
        finally:
            bar.close()
        restored = monitor.restore_best(learner)
        success, value_error = monitor.final
        return StageResult(
            self.stage,
            collector.frames,
            learner.num_updates,
            time.perf_counter() - start,
            success,
            value_error,
            monitor.stopped,
            restored,
            dict(watch.seconds),
            monitor.final_return,
        )

    @functools.cached_property
    def _value(self) -> TensorDictModuleBase:
        """What evaluations read V from: the learner's target networks themselves (live), built
        once instead of copied at every evaluation."""
        return self.learner.value(live=True)

    def evaluate(self, frames: int) -> tuple[float, float, float]:
        """Greedy episodes from the evaluation env's starts; logs and returns three numbers.

        ``success_rate``: episodes that terminate (leave the stage or end the task) before the
        time limit. ``value_error``: ``|V(s_0) - G|`` between the stage's value estimate at the
        start and the discounted return the greedy policy actually got, reduced over the starts
        by ``cfg.value_error_reduce`` (mean or max), a check that the values handed to the
        previous stage have converged. ``discounted_return``: the mean of those returns, the
        stage's objective.
        """
        cfg = self.cfg
        keep_threads()
        max_steps = cfg.eval_max_steps or int(getattr(self.eval_env, "max_steps", 1000))
        stats, rollout = evaluate_policy(self.eval_env, self.learner.policy, max_steps)
        summary = stats.summary()
        returns = discounted_return(rollout, stats.length, self.gammas or float(cfg.gamma))
        with torch.no_grad():
            v0 = self._value(rollout[:, 0].clone()).get("state_value").reshape(-1)
        errors = (v0 - returns).abs()
        summary["value_error"] = (
            errors.max() if cfg.value_error_reduce == "max" else errors.mean()
        ).item()
        summary["discounted_return"] = returns.mean().item()
        self._log({f"eval/stage_{self.stage}/{k}": v for k, v in summary.items()}, frames)
        return summary["success_rate"], summary["value_error"], summary["discounted_return"]

    def _log_batch(self, batch, losses: list[dict[str, torch.Tensor]], frames: int) -> None:
        if self.logger is None:
            return
        done = batch["next", "done"].squeeze(-1)
        metrics = {}
        if done.any():
            metrics["episode_return"] = batch["next", "episode_reward"][done].mean().item()
            metrics["episode_success"] = batch["next", "terminated"][done].float().mean().item()
        for key in dict.fromkeys(k for loss in losses for k in loss):
            metrics[key] = torch.stack([loss[key] for loss in losses if key in loss]).mean().item()
        metrics["updates"] = self.learner.num_updates
        self._log({f"{self.prefix}/{k}": v for k, v in metrics.items()}, frames)

    def _log_position(self) -> dict[str, int]:
        position = getattr(self.logger, "position", None)
        return position() if position is not None else {}

    def _rewind_log(self, position: dict[str, int]) -> None:
        rewind = getattr(self.logger, "rewind", None)
        if rewind is not None:
            rewind(position)

    def _log(self, metrics: dict[str, float | None], step: int) -> None:
        if self.logger is not None:
            for key, value in metrics.items():
                if value is not None:
                    self.logger.log_scalar(key, value, step=step)
