"""The parts every training loop is built from, and the loop itself (:func:`run_loop`): a
collector feeding replay buffers, updates, evaluations with an early stop that keeps the best
weights (:class:`EarlyStop`), metrics (:class:`MetricsLog`, with rewind), checkpoints and
clean stops (:func:`checkpoint_or_stop`), and the time each phase takes (:class:`Stopwatch`).
A stage of the backward or flat schedule (:class:`~torchrl_stages.stage.StageTrainer`) and a
phase of the joint one (:class:`~torchrl_stages.schedules.joint.JointTrainer`) differ only in
what they give :func:`run_loop`."""

from __future__ import annotations

import copy
import logging
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.evaluate import ended_well
from torchrl_stages.preemption import Interrupted, requested
from torchrl_stages.threads import keep_threads

__all__ = [
    "EarlyStop",
    "MetricsLog",
    "Stopwatch",
    "can_stop_early",
    "checkpoint_or_stop",
    "first_evaluation",
    "log_evaluation",
    "loop_state",
    "progress_bar",
    "resume_latest",
    "run_loop",
]


log = logging.getLogger("torchrl_stages")


def progress_bar(
    initial: int, total: int, desc: str, enabled: bool, open_ended: bool = False
) -> tqdm:
    """A stage's (or joint phase's) frame bar, shown only on a terminal (:func:`bar_shown`).
    ``open_ended`` (an early stop may end the loop before ``total``): no total, percentage or
    time left, which would count to a budget the loop seldom reaches; the frames, their rate
    and the budget in the description."""
    if open_ended:
        desc = f"{desc} (budget {total} frames)"
    return tqdm(
        initial=initial,
        total=None if open_ended else total,
        desc=desc,
        unit="frame",
        disable=not bar_shown(enabled),
        leave=False,
    )


def bar_shown(enabled: bool) -> bool:
    """Whether a loop with ``progress=enabled`` shows its bar: on a terminal (stderr) only.
    Elsewhere (a log file, nohup, a batch job, CI) it logs a line per evaluation instead
    (:func:`log_evaluation`)."""
    return enabled and sys.stderr.isatty()


def can_stop_early(cfg: StageConfig) -> bool:
    """Whether an early stop can end a loop of ``cfg`` before its frame budget: a success
    threshold, evaluations, and ``min_frames`` within the budget.

    Examples:
        >>> from torchrl_stages.config import StageConfig
        >>> can_stop_early(StageConfig(success_threshold=0.9, eval_every=1000))
        True
        >>> can_stop_early(StageConfig(success_threshold=None, eval_every=1000))
        False
    """
    return (
        cfg.success_threshold is not None
        and int(cfg.eval_every) > 0
        and int(cfg.min_frames) <= int(cfg.frames)
    )


def log_evaluation(
    where: str,
    frames: int,
    budget: int,
    success: float,
    value_error: float,
    seconds: float,
    seed: int | None = None,
) -> None:
    """One INFO line of the ``torchrl_stages`` logger for one evaluation of a loop (``where``:
    the stage or joint phase; ``seed``: which seed of a seed-stacked loop). A run of
    ``stages-train`` has Hydra send it to the console and to the run's log file.

    Examples:
        >>> shown = logging.StreamHandler(sys.stdout)
        >>> log.addHandler(shown), log.setLevel(logging.INFO)
        (None, None)
        >>> log_evaluation("stage 1 (s1)", 2048, 8192, 0.75, 0.0312, 12.34, seed=3)
        seed 3: stage 1 (s1): 2048 of 8192 frames, success 0.75, value error 0.031, 12.3s
        >>> log.removeHandler(shown), log.setLevel(logging.NOTSET)
        (None, None)
    """
    who = where if seed is None else f"seed {seed}: {where}"
    log.info(
        "%s: %d of %d frames, success %.2f, value error %.3f, %.1fs",
        who,
        frames,
        budget,
        success,
        value_error,
        seconds,
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


def loop_state(
    learner: Any, buffer: Any, collector: Any, eval_env: Any, monitor: Any, counters: dict
) -> dict[str, Any]:
    """What a stage loop's checkpoint holds (besides the process-global generators): the
    learner (weights, optimizers, update count), the replay buffer, the collector, the
    evaluation env's state, the early stop's bookkeeping and the loop's counters."""
    return {
        "learner": StateOf(learner.checkpoint, learner.load_checkpoint),
        "replay_buffer": buffer,
        "collector": collector,
        "eval_env": getattr(eval_env, "base_env", eval_env),
        "monitor": monitor,
        "counters": counters,
    }


def resume_latest(
    checkpoints: StageCheckpoints | None, state: dict[str, Any], log: Any
) -> Path | None:
    """Loads the newest checkpoint (if any) into ``state`` and rewinds ``log`` (a
    :class:`MetricsLog`, or anything with its ``rewind``) to the position it recorded in
    ``state["counters"]["log"]``; returns the checkpoint's path, or ``None``."""
    latest = checkpoints.latest() if checkpoints is not None else None
    if latest is not None:
        checkpoints.load(latest, state)
        log.rewind(state["counters"]["log"])
    return latest


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


class EarlyStop:
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
        learner: nn.Module,
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


class MetricsLog:
    """A loop's metrics: scalars to a torchrl ``logger`` (none: dropped), and the logger's
    position and rewind where it has them (:class:`~torchrl_stages.loggers.CSVMetricsLogger`),
    so that a resumed loop drops the rows of an interrupted attempt. Each call's scalars are
    then shown together to the logger's observers, where it has them
    (:data:`~torchrl_stages.loggers.Observer`: an observer may end the run).

    Examples:
        >>> log = MetricsLog(None)
        >>> log({"train/stage_0/loss": 0.5}, step=128)
        >>> log.position()
        {}
    """

    def __init__(self, logger: Logger | None) -> None:
        self.logger = logger

    def __call__(self, metrics: dict[str, float | None], step: int) -> None:
        if self.logger is None:
            return
        logged = {key: value for key, value in metrics.items() if value is not None}
        for key, value in logged.items():
            self.logger.log_scalar(key, value, step=step)
        notify = getattr(self.logger, "notify", None)
        if notify is not None:
            notify(logged, step)

    def position(self) -> dict[str, int]:
        position = getattr(self.logger, "position", None)
        return position() if position is not None else {}

    def rewind(self, position: dict[str, int]) -> None:
        rewind = getattr(self.logger, "rewind", None)
        if rewind is not None:
            rewind(position)

    @staticmethod
    def episodes(batch: TensorDictBase) -> dict[str, float]:
        """``episode_return`` and ``episode_success`` of the episodes a batch ended."""
        return MetricsLog.episodes_by_row(batch.reshape(1, -1))[0]

    @staticmethod
    def episodes_by_row(batch: TensorDictBase) -> list[dict[str, float]]:
        """:meth:`episodes` of each row of a ``[rows, ...]`` batch (one row per seed), read
        back from the device at once.

        Examples:
            >>> from tensordict import TensorDict
            >>> done = torch.tensor([[True, False], [False, False]]).unsqueeze(-1)
            >>> batch = TensorDict({"next": {"done": done, "terminated": done,
            ...     "episode_reward": torch.tensor([[[2.0], [5.0]], [[1.0], [1.0]]])}}, [2, 2])
            >>> MetricsLog.episodes_by_row(batch)
            [{'episode_return': 2.0, 'episode_success': 1.0}, {}]
        """
        rows = batch.shape[0]
        done = batch["next", "done"].reshape(rows, -1)
        ended = done.to(torch.float64)
        returns = batch["next", "episode_reward"].reshape(rows, -1).to(torch.float64) * ended
        success = (ended_well(batch).reshape(rows, -1) & done).to(torch.float64)
        counts, totals, wins = torch.stack([ended.sum(1), returns.sum(1), success.sum(1)]).tolist()
        return [
            {"episode_return": total / count, "episode_success": win / count} if count else {}
            for count, total, win in zip(counts, totals, wins, strict=True)
        ]

    @staticmethod
    def losses(losses: Sequence[dict[str, torch.Tensor]]) -> dict[str, float]:
        """Each loss entry's mean over a batch's updates."""
        keys = dict.fromkeys(k for loss in losses for k in loss)
        return {
            k: torch.stack([loss[k] for loss in losses if k in loss]).mean().item() for k in keys
        }


def _shown(value: float | Sequence[float], digits: int) -> str:
    """A progress bar's number: one value, or the mean of one per seed."""
    if isinstance(value, Sequence):
        value = sum(value) / len(value)
    return f"{value:.{digits}f}"


def run_loop(
    collector: StageCollector,
    *,
    learn: Callable[[TensorDictBase, int], Any],
    log_batch: Callable[[TensorDictBase, Any], None],
    evaluate: Callable[[], tuple[float, float, float | None]],
    early_stop: EarlyStop,
    model: nn.Module,
    eval_every: int,
    counters: dict[str, Any],
    checkpoints: StageCheckpoints | None,
    state: dict[str, Any],
    clock: tuple[dict[str, Any], float, MetricsLog],
    where: str,
    watch: Stopwatch,
    progress: bool = False,
    count: Callable[[TensorDictBase], int] | None = None,
    open_ended: bool = False,
    seeds: Sequence[int] | None = None,
    training: Callable[[], Sequence[int]] | None = None,
) -> None:
    """The loop: for every collected batch, ``learn(batch, frames)`` (store it, take the
    gradient steps; returns the losses), ``log_batch(batch, losses)``, every ``eval_every``
    frames from ``counters["next_eval"]`` on ``evaluate()`` -> ``(success, value_error,
    return)`` recorded by ``early_stop`` (which keeps ``model``'s best weights) until it says
    stop, then :func:`checkpoint_or_stop`, which first writes the seconds since ``start`` and
    the log's position into ``record`` (``clock = (record, start, log)``). ``count(batch)``
    gives the frames a checkpoint is named by (default: the collector's); ``where`` names the
    loop in messages, on its progress bar (``progress``, on a terminal; ``open_ended``: an
    early stop can end it before its budget, see :func:`progress_bar`) and in the line each
    evaluation logs where the bar is not shown (:func:`log_evaluation`). A seed-stacked loop
    gives its ``seeds`` (evaluations return one number per seed) and ``training()``, the rows
    still training, whose evaluations are logged, each naming its seed."""
    record, start, metrics = clock
    copies = 1 if seeds is None else len(seeds)
    label = where if seeds is None else f"{where}, {copies} seeds"
    report = progress and not bar_shown(progress)

    def before_save() -> None:
        record.update(seconds=time.perf_counter() - start, log=metrics.position())

    def log_lines(success, value_error, rows: Sequence[int]) -> None:
        frames, budget = collector.frames // copies, int(collector.total_frames) // copies
        seconds = time.perf_counter() - start
        if seeds is None:
            log_evaluation(where, frames, budget, success, value_error, seconds)
            return
        for i in rows:
            log_evaluation(where, frames, budget, success[i], value_error[i], seconds, seeds[i])

    bar = progress_bar(collector.frames, int(collector.total_frames), label, progress, open_ended)
    try:
        for batch in watch.timed("collect", collector):
            frames = collector.frames
            total = frames if count is None else count(batch)
            keep_threads()
            losses = learn(batch, frames)
            with watch("log"):
                log_batch(batch, losses)
            bar.update(batch.numel())
            stop = False
            if eval_every > 0 and frames >= counters["next_eval"]:
                counters["next_eval"] += eval_every
                # the seeds training before this evaluation: one that it stops is logged
                rows = list(training() if training is not None else range(copies))
                with watch("evaluate"):
                    success, value_error, ret = evaluate()
                bar.set_postfix(success=_shown(success, 2), value_error=_shown(value_error, 3))
                if report:
                    log_lines(success, value_error, rows)
                stop = early_stop.record(model, success, value_error, frames, ret)
            if stop:
                break
            checkpoint_or_stop(checkpoints, total, state, before_save, label, watch)
    finally:
        bar.close()
