"""One stage's training for any number of seeds (:class:`StageTrainer`: the
:class:`~torchrl_stages.loop.Trainer` over a stage's collector, replay buffer and learner) and
what it returns (:class:`StageResult`).

One seed is the ordinary case: an ordinary learner is one row. Several seeds train at once as
one seed-stacked learner (:mod:`~torchrl_stages.learners.stacking`), one env holding
``num_envs`` copies per seed and one replay storage with a ring per seed
(:class:`~torchrl_stages.replay.SeedReplayBuffer`). Every seed keeps what a run of its own
keeps: its initial weights, its replay contents, its evaluations, its early stop (a seed that
stops keeps the weights it stopped with while the others train on, and is left out of their
updates: :func:`~torchrl_stages.learners.stacking.update_rows`), its best weights and its
metrics. The env's random streams are shared by the seeds, so a seed's run among others is a
draw from the same distribution as its run alone, not the same bits.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.early_stop import Evaluation, SeedEarlyStops, first_evaluation, seed_rows
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.failures import stage_failure
from torchrl_stages.learners import Learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.learners.stacking import unstack_learner, update_rows
from torchrl_stages.loop import LoopCounters, Stopwatch, Trainer, can_stop_early
from torchrl_stages.metric_names import STAGE, metric_name
from torchrl_stages.metrics import MetricsLog, SeedLogs
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import NonFiniteValueError

__all__ = ["StageResult", "StageTrainer", "per_seed_metrics"]

log = logging.getLogger("torchrl_stages")


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


def per_seed_metrics(
    metrics: dict[str, torch.Tensor], rows: torch.Tensor | None, n: int
) -> dict[str, torch.Tensor]:
    """An update's metrics with one entry per seed (``[n]``): an ordinary learner's scalars
    as one, and those computed for ``rows`` alone placed in their rows (NaN in the others).

    Examples:
        >>> per_seed_metrics({"loss": torch.tensor(0.5)}, None, 1)["loss"]
        tensor([0.5000])
        >>> per_seed_metrics({"loss": torch.tensor([0.5])}, torch.tensor([1]), 2)["loss"]
        tensor([   nan, 0.5000])
    """
    out = {}
    for key, value in metrics.items():
        if value.ndim == 0:
            value = value.reshape(1)
        elif rows is not None and value.shape[0] == rows.numel() != n:
            value = value.new_full((n,), float("nan")).index_copy_(0, rows, value)
        out[key] = value
    return out


def loss_means(losses: Sequence[dict[str, torch.Tensor]]) -> dict[str, list[float]]:
    """Each loss entry's mean over a batch's updates, per seed (an entry some updates leave
    out, such as TD3's delayed actor loss: over the others)."""
    keys = dict.fromkeys(k for loss in losses for k in loss)
    return {
        k: torch.stack([loss[k] for loss in losses if k in loss]).mean(0).tolist() for k in keys
    }


class StageTrainer:
    """Trains stage ``stage`` for every seed of ``learner`` (an ordinary learner: one seed).

    ``env`` is the stage's training env (starts inside the stage, transitions terminal, rewards
    rewritten by :class:`~torchrl_stages.transforms.StageTransform`) and ``eval_env`` the same
    kind of env for greedy evaluations and the early stop on ``cfg.success_threshold``; each
    holds one copy of its batch per seed, seed-major (:meth:`~torchrl_stages.task.StagedTask.
    stage_env` with ``copies``). ``cfg``'s frames, batches and evaluation periods are per seed.
    ``logs`` (one :class:`~torchrl_stages.metrics.MetricsLog` per seed) receive each seed's
    metrics; ``seeds`` name the seeds in messages. With ``checkpoints`` the loop saves every
    ``checkpoints.every`` frames and goes on from the newest checkpoint on disk, the logs
    rewound with it, so an interrupted stage goes on exactly where it stopped. ``gammas`` (one
    per stage) makes evaluations compare values with the stage-discounted return; ``postproc``
    transforms each collected batch and ``extra_keys`` are stored with what the loss reads
    (the flat schedule's per-transition discounts); ``on_evaluate(frames)`` runs after every
    evaluation. :meth:`train` returns each seed's ordinary learner (``make_learner()`` builds
    an empty one to take a seed's row out of a stacked learner) and result.

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
        >>> [result.frames for _, result in trainer.train()]  # doctest: +SKIP
        [512]
    """

    def __init__(
        self,
        stage: int,
        learner: Learner,
        env: EnvBase,
        eval_env: EnvBase,
        cfg: StageConfig,
        *,
        logs: Sequence[MetricsLog] | None = None,
        make_learner: Callable[[], Learner] | None = None,
        name: str | None = None,
        progress: bool = False,
        seeds: Sequence[int] | None = None,
        checkpoints: StageCheckpoints | None = None,
        gammas: Sequence[float] | None = None,
        postproc: Callable[[TensorDictBase], TensorDictBase] | None = None,
        extra_keys: Sequence[NestedKey] = (),
        on_evaluate: Callable[[int], None] | None = None,
    ) -> None:
        self.stage, self.learner, self.env, self.eval_env, self.cfg = (
            stage,
            learner,
            env,
            eval_env,
            cfg,
        )
        self.n = int(learner.seeds or 1)
        logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(self.n)]
        if len(logs) != self.n:
            raise ValueError(f"{len(logs)} logs for {self.n} seeds")
        self.logs = SeedLogs(logs)
        self.make_learner = make_learner
        self.seeds = list(seeds) if seeds is not None else list(range(self.n))
        self.name = name or str(stage)
        self.progress, self.checkpoints = progress, checkpoints
        self.gammas, self.postproc, self.on_evaluate = gammas, postproc, on_evaluate
        self.keys = list(dict.fromkeys([*learner.replay_keys, *extra_keys]))

    @functools.cached_property
    def _value(self) -> TensorDictModuleBase:
        """What evaluations read V from: the learner's target networks themselves (live), built
        once instead of copied at every evaluation."""
        return self.learner.value(live=True)

    def train(self) -> list[tuple[Learner, StageResult]]:
        cfg, learner, n = self.cfg, self.learner, self.n
        collector = StageCollector(
            self.env,
            learner.exploration_policy,
            frames_per_batch=int(cfg.frames_per_batch) * n,
            total_frames=int(cfg.frames) * n,
            init_random_frames=int(cfg.init_random_frames) * n,
        )
        buffer = SeedReplayBuffer(int(cfg.buffer_size), num_seeds=n, device=learner.device)
        stops = SeedEarlyStops(cfg, seed_rows(learner))
        counters = LoopCounters(next_eval=first_evaluation(cfg))
        state = {
            "learner": StateOf(learner.checkpoint, learner.load_checkpoint),
            "replay_buffer": buffer,
            "collector": collector,
            "eval_env": getattr(self.eval_env, "base_env", self.eval_env),
            "monitor": stops,
            "counters": counters,
        }
        latest = self.checkpoints.latest() if self.checkpoints is not None else None
        if latest is not None:
            self.checkpoints.load(latest, {"counters": counters})  # first: is it of this form
            self.checkpoints.load(latest, state)
            self.logs.rewind(counters.log)
            seeds = f", {n} seeds" if n > 1 else ""
            log.info("stage %d (%s)%s: resuming from %s", self.stage, self.name, seeds, latest)
        start = stops.start = time.perf_counter() - counters.seconds
        watch = Stopwatch()
        loop = Trainer(
            collector,
            stops,
            counters,
            eval_every=int(cfg.eval_every),
            checkpoints=self.checkpoints,
            state=state,
            seeds=n,
            where=f"stage {self.stage} ({self.name})",
            watch=watch,
            progress=self.progress,
            open_ended=can_stop_early(cfg),
            seed_names=self.seeds,
        )
        loop.register_op("batch", functools.partial(self._store, buffer, watch))
        loop.register_op("update", functools.partial(self._update, buffer, stops, watch))
        loop.register_op(
            "log", lambda batch, losses: self._log_batch(batch, losses, collector, stops.active())
        )
        loop.register_op("evaluate", functools.partial(self.evaluate, active=stops.active))
        if self.on_evaluate is not None:
            loop.register_op("evaluated", lambda ev: self.on_evaluate(collector.frames // n))
        loop.register_op("checkpoint", lambda: self._record(counters, start))
        try:
            loop.train()
        except (NonFiniteError, NonFiniteValueError) as err:
            raise stage_failure(
                err, self.stage, self.name, learner, buffer.held(), stops.rows, self.seeds
            ) from err
        return [self._result(i, stops, collector, start, watch) for i in range(n)]

    def _record(self, counters: LoopCounters, start: float) -> None:
        counters.seconds = time.perf_counter() - start
        counters.log = self.logs.position()

    def _store(self, buffer: SeedReplayBuffer, watch: Stopwatch, batch: TensorDictBase) -> None:
        with watch("collect"):
            if self.postproc is not None:
                batch = self.postproc(batch)
            buffer.extend(batch.select(*self.keys, strict=False))

    def _update(
        self, buffer: SeedReplayBuffer, stops: SeedEarlyStops, watch: Stopwatch, frames: int
    ) -> list[dict[str, torch.Tensor]]:
        """The gradient steps of a batch, for the seeds that have not stopped (a stopped seed's
        row gets no gradient; its stopped weights are restored at the end). One draw for all
        of a batch's steps, split per step: on CPU the same indices as a draw per step (the
        randint stream is the same) unless the update itself draws random numbers in between
        (TD3's target smoothing); one storage read, not one per step."""
        cfg, learner, n = self.cfg, self.learner, self.n
        learner.anneal(frames)
        losses: list[dict[str, torch.Tensor]] = []
        if frames < cfg.init_random_frames:
            return losses
        steps = int(cfg.updates_per_batch)
        draws, per_draw = (steps, 1) if learner.update_draws_random else (min(steps, 1), steps)
        active = stops.active()
        rows = None if len(active) == n else torch.tensor(active, device=learner.device)
        for _ in range(draws):
            with watch("sample"):
                drawn = buffer.sample(int(cfg.batch_size) * per_draw, rows)
                if learner.seeds is None:  # an ordinary learner reads [batch] samples
                    drawn = drawn[0]
                samples = drawn.split(int(cfg.batch_size), dim=-1)
            for sample in samples:
                with watch("update"), update_rows(rows):
                    keep_threads()
                    losses.append(per_seed_metrics(learner.update(sample), rows, n))
        learner.check_finite()
        return losses

    def evaluate(self, frames: int, active: Callable[[], list[int]] | None = None) -> Evaluation:
        """Greedy episodes from the evaluation env's starts, for each seed (the ``active`` ones
        log theirs under ``eval/stage_<k>/``).

        ``success_rate``: episodes that leave the stage or end the task solved
        (:func:`~torchrl_stages.evaluate.ended_well`: terminated, or the env's success flag)
        before the time limit. ``value_error``: ``|V(s_0) - G|`` between the stage's value
        estimate at the start and the discounted return the greedy policy actually got, reduced
        over the starts by ``cfg.value_error_reduce`` (mean or max), a check that the values
        handed to the previous stage have converged. ``discounted_return``: the mean of those
        returns, the stage's objective.
        """
        cfg, n = self.cfg, self.n
        max_steps = cfg.eval_max_steps or int(getattr(self.eval_env, "max_steps", 1000))
        summaries = evaluate_greedy(
            self.eval_env,
            self.learner.policy,
            self._value,
            max_steps,
            self.gammas or float(cfg.gamma),
            cfg.value_error_reduce,
            groups=n,
        )
        for i in active() if active is not None else range(n):
            self.logs[i](
                {metric_name("eval", STAGE, self.stage, k): v for k, v in summaries[i].items()},
                frames,
            )
        return Evaluation(
            [s["success_rate"] for s in summaries],
            [s["value_error"] for s in summaries],
            [s["discounted_return"] for s in summaries],
            [frames] * n,
            [self.learner.num_updates] * n,
        )

    def _log_batch(
        self, batch: TensorDictBase, losses: list[dict], collector, active: list[int]
    ) -> None:
        if self.logs.silent:
            return
        n, frames = self.n, collector.frames // self.n
        episodes = MetricsLog.episodes_by_row(batch.reshape(n, -1))
        means = loss_means(losses)
        for i in active:
            metrics = {**episodes[i], **{k: v[i] for k, v in means.items()}}
            metrics["updates"] = self.learner.num_updates
            named = {metric_name("train", STAGE, self.stage, k): v for k, v in metrics.items()}
            self.logs[i](named, frames)

    def _result(
        self, i: int, stops: SeedEarlyStops, collector, start: float, watch: Stopwatch
    ) -> tuple[Learner, StageResult]:
        """Seed ``i``'s learner (its weights put back: those it stopped with, or its best) and
        result."""
        at, early = stops.stopped_at[i], stops.monitors[i]
        restored = stops.finish(i)
        success, value_error = early.final
        result = StageResult(
            self.stage,
            collector.frames // self.n if at is None else at["frames"],
            self.learner.num_updates if at is None else at["updates"],
            time.perf_counter() - start if at is None else at["seconds"],
            success,
            value_error,
            early.stopped,
            restored,
            dict(watch.seconds),
            early.final_return,
        )
        if self.learner.seeds is None:
            return self.learner, result
        plain = unstack_learner(self.learner, i, self.make_learner())
        plain.num_updates = result.updates
        return plain, result
