"""The loop every schedule runs (:class:`Trainer`): a collector's batches, each stored,
learned from and logged, an evaluation every ``eval_every`` frames with an early stop over each
seed, and checkpoints with clean stops on a signal. What a schedule does at each point is a
hook registered by name (:meth:`Trainer.register_op`), as in torchrl's ``Trainer``; what the
loop counts is a :class:`LoopCounters`, saved with every checkpoint. A stage of the backward or
flat schedule (:class:`~torchrl_stages.stage.StageTrainer`) and a phase of the joint one
(:class:`~torchrl_stages.schedules.joint.JointTrainer`) are compositions of these hooks."""

from __future__ import annotations

import logging
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from tqdm.auto import tqdm

from torchrl_stages.checkpoint import CHECKPOINT_FORMAT, SavedCounters, StageCheckpoints
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.early_stop import Evaluation, SeedEarlyStops
from torchrl_stages.preemption import Interrupted, requested
from torchrl_stages.threads import keep_threads

__all__ = [
    "LoopCounters",
    "Stopwatch",
    "Trainer",
    "can_stop_early",
    "log_evaluation",
    "progress_bar",
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


@dataclass
class LoopCounters(SavedCounters):
    """What a loop counts, saved with its checkpoints: the frames (per seed) of its next
    evaluation, the training seconds of earlier launches, and the logs' positions at the last
    checkpoint (a resumed loop rewinds its logs to them).

    Examples:
        >>> counters = LoopCounters(next_eval=64)
        >>> counters.load_state_dict({"next_eval": 128, "seconds": 2.0, "log": {}, "format": 2})
        >>> counters.next_eval, counters.state_dict()["seconds"]
        (128, 2.0)
    """

    next_eval: int
    seconds: float = 0.0
    log: dict[str, Any] = field(default_factory=dict)
    format: int = CHECKPOINT_FORMAT  # what a resumed loop checks first


def _shown(value: float | Sequence[float], digits: int) -> str:
    """A progress bar's number: one value, or the mean of one per seed."""
    if isinstance(value, Sequence):
        value = sum(value) / len(value)
    return f"{value:.{digits}f}"


#: the hook points of :class:`Trainer`, in the order a batch meets them
HOOKS = ("batch", "update", "log", "evaluate", "evaluated", "checkpoint")


class Trainer:
    """The loop: for every batch of ``collector`` (``seeds`` equal, seed-major parts), the
    registered hooks in turn:

    - ``batch(batch)``: the batch was collected (store it);
    - ``update(frames) -> losses``: the gradient steps (``frames``: each seed's so far);
    - ``log(batch, losses)``;
    - every ``eval_every`` frames (per seed) from ``counters.next_eval`` on:
      ``evaluate(frames) -> Evaluation``, recorded by ``early_stop``, then
      ``evaluated(evaluation)``; the loop ends once every seed has stopped;
    - ``checkpoint()`` before a checkpoint is written (when one is due, or a stop was asked for:
      :mod:`torchrl_stages.preemption`, which then raises
      :class:`~torchrl_stages.preemption.Interrupted`). ``state`` is what a checkpoint holds;
      its name is ``frames_before`` plus each seed's frames.

    ``where`` names the loop in messages, on its progress bar (``progress``, on a terminal;
    ``open_ended``: an early stop can end it before its budget, see :func:`progress_bar`) and
    in the line each evaluation of a seed still training logs where the bar is not shown
    (:func:`log_evaluation`; several seeds: each line names its seed of ``seed_names``);
    ``watch`` times its phases.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> policy = TensorDictModule(lambda o: torch.zeros(o.shape[:-1], dtype=torch.long),
        ...                           ["observation"], ["action"])
        >>> collector = StageCollector(GridWorldEnv((4,)), policy, frames_per_batch=8,
        ...                            total_frames=32)
        >>> loop = Trainer(collector, SeedEarlyStops(DQNConfig(), [None]), LoopCounters(0))
        >>> seen = []
        >>> loop.register_op("batch", lambda batch: seen.append(batch.numel()))
        >>> loop.train()
        >>> seen
        [8, 8, 8, 8]
    """

    def __init__(
        self,
        collector: StageCollector,
        early_stop: SeedEarlyStops,
        counters: LoopCounters,
        *,
        eval_every: int = 0,
        checkpoints: StageCheckpoints | None = None,
        state: dict[str, Any] | None = None,
        seeds: int = 1,
        frames_before: int = 0,
        where: str = "the loop",
        watch: Stopwatch | None = None,
        progress: bool = False,
        open_ended: bool = False,
        seed_names: Sequence[int] | None = None,
    ) -> None:
        self.collector, self.early_stop, self.counters = collector, early_stop, counters
        self.eval_every, self.checkpoints, self.state = int(eval_every), checkpoints, state or {}
        self.seeds, self.frames_before, self.where = int(seeds), int(frames_before), where
        self.watch = watch if watch is not None else Stopwatch()
        self.progress, self.open_ended = progress, open_ended
        self.seed_names = list(seed_names) if seed_names is not None else list(range(self.seeds))
        self.label = where + (f", {self.seeds} seeds" if self.seeds > 1 else "")
        self.ops: dict[str, list[Callable[..., Any]]] = {point: [] for point in HOOKS}

    def register_op(self, point: str, op: Callable[..., Any]) -> None:
        """Runs ``op`` at hook ``point`` (one of :data:`HOOKS`); ``update`` and ``evaluate``
        take one op each, whose result the loop uses."""
        if point not in self.ops:
            raise ValueError(f"unknown hook point {point!r} (known: {', '.join(HOOKS)})")
        if point in ("update", "evaluate") and self.ops[point]:
            raise ValueError(f"the {point!r} hook is registered already")
        self.ops[point].append(op)

    def _call(self, point: str, *args: Any) -> Any:
        out = None
        for op in self.ops[point]:
            out = op(*args)
        return out

    def train(self) -> None:
        """Runs the loop to the collector's budget or every seed's early stop."""
        collector, counters, watch, n = self.collector, self.counters, self.watch, self.seeds
        budget = int(collector.total_frames)
        bar = progress_bar(collector.frames, budget, self.label, self.progress, self.open_ended)
        report = self.progress and not bar_shown(self.progress)
        try:
            for batch in watch.timed("collect", collector):
                frames = collector.frames // n
                keep_threads()
                self._call("batch", batch)
                losses = self._call("update", frames)
                with watch("log"):
                    self._call("log", batch, losses)
                bar.update(batch.numel())
                if self.eval_every > 0 and frames >= counters.next_eval:
                    counters.next_eval += self.eval_every
                    rows = self.early_stop.active()  # a seed this evaluation stops is logged
                    with watch("evaluate"):
                        evaluation: Evaluation = self._call("evaluate", frames)
                    bar.set_postfix(
                        success=_shown(evaluation.success, 2),
                        value_error=_shown(evaluation.value_error, 3),
                    )
                    if report:
                        self._log_lines(evaluation, rows, frames, budget // n)
                    stop = self.early_stop.record(evaluation)
                    self._call("evaluated", evaluation)
                    if stop:
                        break
                self._checkpoint_or_stop(self.frames_before + frames)
        finally:
            bar.close()

    def _log_lines(self, evaluation: Evaluation, rows: list[int], frames: int, budget: int) -> None:
        seconds = time.perf_counter() - self.early_stop.start
        for i in rows:
            seed = self.seed_names[i] if self.seeds > 1 else None
            success, value_error = evaluation.success[i], evaluation.value_error[i]
            log_evaluation(self.where, frames, budget, success, value_error, seconds, seed)

    def _checkpoint_or_stop(self, frames: int) -> None:
        signum = requested()
        if self.checkpoints is not None and (self.checkpoints.due(frames) or signum is not None):
            with self.watch("checkpoint"):
                self._call("checkpoint")
                self.checkpoints.save(frames, self.state)
        if signum is not None:
            raise Interrupted(signum, f"{self.label} at {frames} frames")
