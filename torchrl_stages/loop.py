"""The loop every schedule runs (:class:`Trainer`: named hooks over a collector's batches, typed
counters) and what a trainer of several seeds builds it with (:class:`SeedLoop`)."""

from __future__ import annotations

import logging
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import KW_ONLY, dataclass, field
from statistics import fmean
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from torchrl_stages.checkpoint import CHECKPOINT_FORMAT, SavedCounters, StageCheckpoints
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.early_stop import Evaluation, SeedEarlyStops, can_stop_early, first_evaluation
from torchrl_stages.metric_names import STAGE, metric_name
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.preemption import Interrupted, requested
from torchrl_stages.threads import keep_threads

__all__ = ["LoopCounters", "SeedLoop", "Stopwatch", "Trainer", "loss_means"]

log = logging.getLogger("torchrl_stages")

#: the hook points of :class:`Trainer`, in the order a batch meets them
HOOKS = ("batch", "update", "log", "evaluate", "evaluated", "checkpoint")


def loss_means(losses: Sequence[dict[str, torch.Tensor]]) -> dict[str, list[float]]:
    """Each loss entry's mean over the batch's updates that have it (TD3: actor), per seed."""
    keys = dict.fromkeys(k for loss in losses for k in loss)
    return {k: torch.stack([x[k] for x in losses if k in x]).mean(0).tolist() for k in keys}


@dataclass
class Stopwatch:
    """Wall-clock seconds spent in named phases of a loop.

    Examples:
        >>> watch = Stopwatch()
        >>> with watch("update"):
        ...     pass
        >>> list(watch.seconds)
        ['update']
    """

    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - start

    def timed(self, phase: str, iterable):
        """Yields from ``iterable``, timing each ``next`` as ``phase``."""
        iterator, end = iter(iterable), object()
        while True:
            with self(phase):
                item = next(iterator, end)
            if item is end:
                return
            yield item


@dataclass
class LoopCounters(SavedCounters):
    """What a loop counts, saved with its checkpoints (``log``: the logs' positions).

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


@dataclass(eq=False)
class Trainer:
    """The loop: per batch of ``collector`` (``seeds`` equal, seed-major parts) the hooks
    ``batch(batch)``, ``update(frames) -> losses``, ``log(batch, losses)``; every ``eval_every``
    frames ``evaluate(frames) -> Evaluation``, ``evaluated(evaluation)``; ``checkpoint()`` before
    ``state`` is checkpointed (when due, or on a stop request, then raising
    :class:`~torchrl_stages.preemption.Interrupted`). It ends at the budget or once every seed
    has stopped.

    Examples:
        >>> from torchrl_stages.envs import GridWorldEnv
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> collector = StageCollector(GridWorldEnv((4,)), None, frames_per_batch=8,
        ...                            total_frames=32, init_random_frames=32)  # random actions
        >>> stops = SeedEarlyStops(DQNConfig(eval_every=0), [None])
        >>> loop = Trainer(collector, stops, LoopCounters(0))
        >>> seen = []
        >>> loop.register_op("batch", lambda batch: seen.append(batch.numel()))
        >>> loop.register_op("batch", lambda batch: seen.append("then"))
        >>> loop.train()
        >>> seen
        [8, 'then', 8, 'then', 8, 'then', 8, 'then']
    """

    collector: StageCollector
    early_stop: SeedEarlyStops
    counters: LoopCounters
    _: KW_ONLY
    checkpoints: StageCheckpoints | None = None
    state: dict[str, Any] = field(default_factory=dict)
    seeds: Sequence[int] = (0,)
    where: str = "the loop"
    watch: Stopwatch = field(default_factory=Stopwatch)
    progress: bool = False
    frames_before: int = field(default=0, init=False)  # the frames of the loops before this one

    def __post_init__(self) -> None:
        n = len(self.seeds)
        self.label = self.where + (f", {n} seeds" if n > 1 else "")
        self.ops: dict[str, list[Callable[..., Any]]] = {point: [] for point in HOOKS}

    def register_op(self, point: str, op: Callable[..., Any]) -> None:
        """Runs ``op`` at hook ``point``, after those registered before (``update`` and
        ``evaluate``: one op, whose result counts)."""
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
        collector, counters, watch, n = self.collector, self.counters, self.watch, len(self.seeds)
        budget, open_ended = int(collector.total_frames), can_stop_early(self.early_stop.cfg)
        eval_every = int(self.early_stop.cfg.eval_every)
        shown = self.progress and sys.stderr.isatty()  # elsewhere: a line per evaluation
        report = self.progress and not shown
        with tqdm(
            initial=collector.frames,
            total=None if open_ended else budget,
            desc=f"{self.label} (budget {budget} frames)" if open_ended else self.label,
            unit="frame",
            disable=not shown,
            leave=False,
        ) as bar:
            for batch in watch.timed("collect", collector):
                frames = collector.frames // n
                keep_threads()
                self._call("batch", batch)
                losses = self._call("update", frames)
                with watch("log"):
                    self._call("log", batch, losses)
                bar.update(batch.numel())
                if eval_every > 0 and frames >= counters.next_eval:
                    counters.next_eval += eval_every
                    rows = self.early_stop.active()  # a seed this evaluation stops is logged
                    with watch("evaluate"):
                        evaluation: Evaluation = self._call("evaluate", frames)
                    bar.set_postfix(  # the mean over the seeds
                        success=f"{fmean(evaluation.success):.2f}",
                        value_error=f"{fmean(evaluation.value_error):.3f}",
                    )
                    if report:
                        self._log_lines(evaluation, rows, frames, budget // n)
                    stop = self.early_stop.record(evaluation)
                    self._call("evaluated", evaluation)
                    if stop:
                        break
                self._checkpoint_or_stop(self.frames_before + frames)

    def _log_lines(self, evaluation: Evaluation, rows: list[int], frames: int, budget: int) -> None:
        seconds = time.perf_counter() - self.early_stop.start
        for i in rows:
            who = self.where if len(self.seeds) == 1 else f"seed {self.seeds[i]}: {self.where}"
            log.info(
                f"{who}: {frames} of {budget} frames, success {evaluation.success[i]:.2f}, "
                f"value error {evaluation.value_error[i]:.3f}, {seconds:.1f}s"
            )

    def _checkpoint_or_stop(self, frames: int) -> None:
        signum = requested()
        if self.checkpoints is not None and (self.checkpoints.due(frames) or signum is not None):
            with self.watch("checkpoint"):
                self._call("checkpoint")
                self.checkpoints.save(frames, self.state)
        if signum is not None:
            raise Interrupted(signum, f"{self.label} at {frames} frames")


class SeedLoop:
    """What a trainer of ``n`` seeds shares: a log per seed, checkpoints, its :class:`Trainer`."""

    def __init__(
        self,
        n: int,
        logs: Sequence[MetricsLog] | None,
        seeds: Sequence[int] | None,
        progress: bool,
        checkpoints: StageCheckpoints | None,
    ) -> None:
        logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
        if len(logs) != n:
            raise ValueError(f"{len(logs)} logs for {n} seeds")
        self.n, self.logs = n, logs
        self.seeds = list(seeds) if seeds is not None else list(range(n))
        self.progress, self.checkpoints = progress, checkpoints

    def latest(self, counters: SavedCounters, where: str, state: dict[str, Any]) -> str | None:
        """The newest checkpoint that loads whole, loaded into ``counters`` (its form checked
        first) and ``state`` (loaded again by :meth:`restore`, once the loop is built)."""
        if self.checkpoints is None:
            return None
        latest = self.checkpoints.latest({"counters": counters, **state})
        if latest is not None:
            seeds = f", {self.n} seeds" if self.n > 1 else ""
            log.info("%s%s: resuming from %s", where, seeds, latest)
        return latest

    def restore(self, latest: str, state: dict[str, Any], counters: SavedCounters) -> None:
        """Loads ``state`` from checkpoint ``latest`` and rewinds the logs to it."""
        self.checkpoints.load(latest, state)
        for i, log in enumerate(self.logs):
            log.rewind(counters.log.get(str(i), {}))

    def record(self, saved: SavedCounters, start: float) -> None:
        """Puts the seconds since ``start`` and each seed's log position in ``saved``."""
        saved.seconds = time.perf_counter() - start
        saved.log = {str(i): log.position() for i, log in enumerate(self.logs)}

    def loop(
        self,
        cfg: StageConfig,
        env: EnvBase,
        policy: Callable[[TensorDictBase], TensorDictBase],
        eval_env: EnvBase,
        rows: Sequence[Any],
        state: dict[str, Any],
        where: str,
        watch: Stopwatch,
        *,
        saved: SavedCounters | None = None,
        latest: str | None = None,
        start: float | None = None,
        init_random: bool = True,
    ) -> Trainer:
        """The :class:`Trainer` of ``cfg`` over ``env``: collector, early stops of ``rows`` and
        counters join ``state``, restored from ``latest``; ``saved`` (default: those counters)
        takes the seconds and log positions; ``start`` (default: from ``saved``) times stops."""
        n = self.n
        collector = StageCollector(
            env,
            policy,
            frames_per_batch=int(cfg.frames_per_batch) * n,
            total_frames=int(cfg.frames) * n,
            init_random_frames=int(cfg.init_random_frames) * n if init_random else 0,
        )
        stops = SeedEarlyStops(cfg, rows)
        counters = LoopCounters(next_eval=first_evaluation(cfg))
        saved = counters if saved is None else saved
        state = {
            **state,
            "collector": collector,
            "eval_env": getattr(eval_env, "base_env", eval_env),
            "monitor": stops,
            "counters" if saved is counters else "phase_counters": counters,
        }
        if latest is not None:
            self.restore(latest, state, saved)
        stops.start = time.perf_counter() - saved.seconds if start is None else start
        loop = Trainer(
            collector,
            stops,
            counters,
            checkpoints=self.checkpoints,
            state=state,
            seeds=self.seeds,
            progress=self.progress,
            where=where,
            watch=watch,
        )
        loop.register_op("checkpoint", lambda: self.record(saved, stops.start))
        return loop

    def log_evaluation(
        self,
        summaries: Sequence[dict[str, float]],
        scope: str,
        index: int,
        active: Sequence[int],
        steps: Sequence[int],
        frames: list[int],
        updates: list[int],
    ) -> Evaluation:
        """Logs each ``active`` seed's ``summaries`` at its ``steps``; every seed's evaluation."""
        for i in active:
            metrics = {metric_name("eval", scope, index, k): v for k, v in summaries[i].items()}
            self.logs[i](metrics, steps[i])
        keys = ("success_rate", "value_error", "discounted_return")
        return Evaluation(*([s[k] for s in summaries] for k in keys), frames, updates)

    def log_batch(
        self,
        batch: TensorDictBase,
        scope: str,
        index: int,
        losses: dict[int, list[dict]],
        updates: Sequence[Mapping[int, int] | Sequence[int]],
        active: Sequence[int],
        steps: Sequence[int],
    ) -> None:
        """Each ``active`` seed's episodes of ``batch`` under ``train/<scope>_<index>/``, and
        each stage m's mean ``losses`` and ``updates[seed][m]`` under ``train/stage_<m>/``."""
        if all(log.logger is None for log in self.logs):
            return
        episodes = MetricsLog.episodes_by_row(batch.reshape(self.n, -1))
        means = {m: loss_means(stage_losses) for m, stage_losses in losses.items()}
        for i in active:
            metrics = {metric_name("train", scope, index, k): v for k, v in episodes[i].items()}
            for m, stage_means in means.items():
                values = {k: v[i] for k, v in stage_means.items()}
                if values and all(v != v for v in values.values()):  # seed i's stage m waits
                    continue
                for k, value in {**values, "updates": updates[i][m]}.items():
                    metrics[metric_name("train", STAGE, m, k)] = value
            self.logs[i](metrics, steps[i])
