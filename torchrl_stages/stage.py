"""One stage's training (:class:`StageTrainer`: the loop of :mod:`torchrl_stages.loop` over a
stage's collector, replay buffer and learner), what it returns and how it fails."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.learners import Learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.loop import (
    EarlyStop,
    MetricsLog,
    Stopwatch,
    can_stop_early,
    first_evaluation,
    loop_state,
    resume_latest,
    run_loop,
)
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
        >>> trainer.train().frames  # doctest: +SKIP
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
        self.log = MetricsLog(logger)
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
        monitor = EarlyStop(cfg)
        counters = {"next_eval": first_evaluation(cfg), "seconds": 0.0, "log": {}}
        state = loop_state(learner, buffer, collector, self.eval_env, monitor, counters)
        resume_latest(self.checkpoints, state, self.log)
        start = time.perf_counter() - counters["seconds"]
        watch = Stopwatch()

        def learn(batch: TensorDictBase, frames: int) -> list[dict[str, torch.Tensor]]:
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
            return losses

        def evaluate() -> tuple[float, float, float]:
            frames = collector.frames
            result = self.evaluate(frames)
            if self.on_evaluate is not None:
                self.on_evaluate(frames)
            return result

        try:
            run_loop(
                collector,
                learn=learn,
                log_batch=lambda batch, losses: self._log_batch(batch, losses, collector.frames),
                evaluate=evaluate,
                early_stop=monitor,
                model=learner,
                eval_every=int(cfg.eval_every),
                counters=counters,
                checkpoints=self.checkpoints,
                state=state,
                clock=(counters, start, self.log),
                where=f"stage {self.stage} ({self.name})",
                watch=watch,
                progress=self.progress,
                open_ended=can_stop_early(cfg),
            )
        except (NonFiniteError, NonFiniteValueError) as err:
            raise stage_failure(err, self.stage, self.name, learner, buffer) from err
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

        ``success_rate``: episodes that leave the stage or end the task solved
        (:func:`~torchrl_stages.evaluate.ended_well`: terminated, or the env's success flag)
        before the time limit. ``value_error``: ``|V(s_0) - G|`` between the stage's value
        estimate at the start and the discounted return the greedy policy actually got, reduced
        over the starts by ``cfg.value_error_reduce`` (mean or max), a check that the values
        handed to the previous stage have converged. ``discounted_return``: the mean of those
        returns, the stage's objective.
        """
        cfg = self.cfg
        max_steps = cfg.eval_max_steps or int(getattr(self.eval_env, "max_steps", 1000))
        summary = evaluate_greedy(
            self.eval_env,
            self.learner.policy,
            self._value,
            max_steps,
            self.gammas or float(cfg.gamma),
            cfg.value_error_reduce,
        )
        self.log({f"eval/stage_{self.stage}/{k}": v for k, v in summary.items()}, frames)
        return summary["success_rate"], summary["value_error"], summary["discounted_return"]

    def _log_batch(self, batch, losses: list[dict[str, torch.Tensor]], frames: int) -> None:
        if self.log.logger is None:
            return
        metrics = {**MetricsLog.episodes(batch), **MetricsLog.losses(losses)}
        metrics["updates"] = self.learner.num_updates
        self.log({f"{self.prefix}/{k}": v for k, v in metrics.items()}, frames)
