"""One stage of many seeds in one process: :class:`SeedsStageTrainer`.

It trains every seed of a stage at once: one seed-stacked learner
(:mod:`~torchrl_stages.learners.stacking`), one env holding ``num_envs`` copies per seed, one
replay storage with a part per seed (:class:`~torchrl_stages.replay.SeedReplayBuffer`), and the
loop of :func:`~torchrl_stages.loop.run_loop`. Every seed keeps what a run of its own keeps:
its initial weights (those of a single run with that seed), its replay contents, its
evaluations, its early stop (a seed that stops keeps the weights it stopped with while the
others train on, and is left out of their updates:
:func:`~torchrl_stages.learners.stacking.update_rows`), its best weights and its metrics.
The env's random streams are shared by the seeds, so a seed's run is a draw from the same
distribution as a single run's, not the same bits.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.collector import StageCollector
from torchrl_stages.config import StageConfig
from torchrl_stages.evaluate import evaluate_greedy_groups
from torchrl_stages.learners import Learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.learners.stacking import (
    seed_axes,
    stack_learners,
    unstack_learner,
    update_rows,
)
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
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.stage import DivergenceError, StageResult
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import NonFiniteValueError

__all__ = [
    "SeedRow",
    "SeedsEarlyStop",
    "SeedsStageTrainer",
    "TeamRow",
    "finished_for_every_seed",
    "metrics_per_seed",
    "seed_stacked_learner",
    "start_stage_logs",
    "train_and_keep",
]

log = logging.getLogger("torchrl_stages")


def _finite(state: dict[str, torch.Tensor]) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point())


def metrics_per_seed(
    metrics: dict[str, torch.Tensor], rows: torch.Tensor | None, n: int
) -> dict[str, torch.Tensor]:
    """An update's metrics with one entry per seed (``[n]``): those computed for ``rows`` alone
    are placed in their rows (NaN in the others)."""
    if rows is None:
        return metrics
    out = {}
    for key, value in metrics.items():
        if value.ndim == 1 and value.shape[0] == rows.numel() != n:
            value = value.new_full((n,), float("nan")).index_copy_(0, rows, value)
        out[key] = value
    return out


class SeedRow:
    """Seed ``seed``'s row of a seed-stacked learner, as :class:`~torchrl_stages.loop.EarlyStop`
    reads and restores a learner: ``state_dict`` copies the row out, ``load_state_dict`` writes
    it back (entries shared by the seeds, such as the exploration schedule, are left alone)."""

    def __init__(self, learner: Learner, seed: int) -> None:
        self.learner, self.seed = learner, seed
        self.axes = {k: a for k, a in seed_axes(learner).items() if a is not None}

    def state_dict(self) -> dict[str, torch.Tensor]:
        state = self.learner.state_dict()
        return {k: state[k].select(axis, self.seed).clone() for k, axis in self.axes.items()}

    @torch.no_grad()
    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        own = self.learner.state_dict(keep_vars=True)
        for key, value in state.items():
            own[key].data.select(self.axes[key], self.seed).copy_(value)


class TeamRow:
    """Seed ``seed``'s row of every seed-stacked learner of ``learners`` as one
    :class:`SeedRow` (entries ``<m>.<key>``: learner ``m``'s): what a whole-task early stop
    keeps and restores of one seed.

    Examples:
        >>> from torchrl.data import Categorical
        >>> from torchrl_stages.learners import StageSpecs, make_learner
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> specs = StageSpecs(["observation"], 3, "action", Categorical(2, (1,)))
        >>> team = [make_learner(DQNConfig(num_cells=[8]), specs, seeds=2) for _ in range(2)]
        >>> row = TeamRow(team, 1)
        >>> state = row.state_dict()  # learner 1's target network, seed 1's row
        >>> state["1.loss.target_value_network_params.module.0.module.value.2.weight"].shape
        torch.Size([1, 8])
    """

    def __init__(self, learners: Sequence[Learner], seed: int) -> None:
        self.rows = [SeedRow(learner, seed) for learner in learners]

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {
            f"{m}.{k}": v for m, row in enumerate(self.rows) for k, v in row.state_dict().items()
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        for m, row in enumerate(self.rows):
            prefix = f"{m}."
            row.load_state_dict(
                {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
            )


class SeedsEarlyStop:
    """One :class:`~torchrl_stages.loop.EarlyStop` per seed: :meth:`record` takes one
    evaluation per seed and says whether every seed has stopped; a seed that stops has its
    weights (its row of each learner, ``rows[i]``), frames, updates and seconds kept
    (:attr:`stopped_at`)."""

    def __init__(self, cfg: StageConfig, rows: Sequence[Any], start: float = 0.0) -> None:
        self.start = start  # what stop times are measured from
        self.rows = list(rows)
        self.monitors = [EarlyStop(cfg) for _ in self.rows]
        self.stopped_at: list[dict | None] = [None] * len(self.rows)

    def record(
        self,
        updates: Sequence[int] | int,
        success: Sequence[float],
        value_error: Sequence[float],
        frames: Sequence[int] | int,
        ret: Sequence[float | None],
    ) -> bool:
        """``updates`` and ``frames``: each seed's so far (one number: the same for all)."""
        n = len(self.monitors)
        updates = [updates] * n if isinstance(updates, int) else list(updates)
        frames = [frames] * n if isinstance(frames, int) else list(frames)
        for i, monitor in enumerate(self.monitors):
            if self.stopped_at[i] is not None:
                continue
            if monitor.record(self.rows[i], success[i], value_error[i], frames[i], ret[i]):
                self.stopped_at[i] = {
                    "state": copy.deepcopy(self.rows[i].state_dict()),
                    "frames": frames[i],
                    "updates": updates[i],
                    "seconds": time.perf_counter() - self.start,
                }
        return all(at is not None for at in self.stopped_at)

    def active(self) -> list[int]:
        return [i for i, at in enumerate(self.stopped_at) if at is None]

    def state_dict(self) -> dict:
        return {
            "monitors": [monitor.state_dict() for monitor in self.monitors],
            "stopped_at": [at or {} for at in self.stopped_at],
        }

    def load_state_dict(self, state: dict) -> None:
        monitors, stopped = state["monitors"], state["stopped_at"]
        if len(monitors) != len(self.monitors) or len(stopped) != len(self.monitors):
            raise ValueError(f"a state of {len(monitors)} seeds, not {len(self.monitors)}")
        for monitor, saved in zip(self.monitors, monitors, strict=True):
            monitor.load_state_dict(saved)
        self.stopped_at = [dict(at) if at else None for at in stopped]


class _SeedLogs:
    """The seeds' metrics logs as one, for a checkpoint: their positions, and their rewind."""

    def __init__(self, logs: Sequence[MetricsLog]) -> None:
        self.logs = logs

    def position(self) -> dict[str, dict[str, int]]:
        return {str(i): log.position() for i, log in enumerate(self.logs)}

    def rewind(self, position: dict[str, dict[str, int]]) -> None:
        for i, log in enumerate(self.logs):
            log.rewind(position.get(str(i), {}))


class SeedsStageTrainer:
    """Trains stage ``stage`` for every seed of the seed-stacked ``learner`` at once.

    ``env`` and ``eval_env`` hold one copy of the stage's training and evaluation batches per
    seed, seed-major (:meth:`~torchrl_stages.task.StagedTask.stage_env` with ``copies``);
    ``cfg``'s frames, batches and evaluation periods are per seed. ``logs`` (one per seed)
    receive each seed's metrics under the keys a single run logs; ``seeds`` name the rows in
    messages (default: 0, 1, ...). With ``checkpoints`` the loop saves the state of every seed
    together every ``checkpoints.every`` frames per seed and goes on from the newest one on
    disk, the seeds' logs rewound with it. ``gammas``, ``postproc`` and ``extra_keys`` are
    :class:`~torchrl_stages.stage.StageTrainer`'s (the flat schedule's per-stage discounts).
    :meth:`train` returns each seed's ordinary learner (``make_learner()`` builds an empty one)
    and result.
    """

    def __init__(
        self,
        stage: int,
        learner: Learner,
        env: EnvBase,
        eval_env: EnvBase,
        cfg: StageConfig,
        *,
        logs: Sequence[MetricsLog],
        make_learner: Callable[[], Learner],
        name: str | None = None,
        progress: bool = False,
        seeds: Sequence[int] | None = None,
        checkpoints: StageCheckpoints | None = None,
        gammas: Sequence[float] | None = None,
        postproc: Callable[[TensorDictBase], TensorDictBase] | None = None,
        extra_keys: Sequence[NestedKey] = (),
    ) -> None:
        self.gammas, self.postproc = gammas, postproc
        self.keys = list(dict.fromkeys([*learner.replay_keys, *extra_keys]))
        self.stage, self.learner, self.env, self.eval_env, self.cfg = (
            stage,
            learner,
            env,
            eval_env,
            cfg,
        )
        self.n = int(learner.seeds or 0)
        if len(logs) != self.n:
            raise ValueError(f"{len(logs)} logs for {self.n} seeds")
        self.logs, self.make_learner = list(logs), make_learner
        self.name = name or str(stage)
        self.progress = progress
        self.seeds = list(seeds) if seeds is not None else list(range(self.n))
        self.prefix = f"train/stage_{stage}"
        self.checkpoints = checkpoints

    def train(self) -> list[tuple[Learner, StageResult]]:
        cfg, learner, n = self.cfg, self.learner, self.n
        collector = StageCollector(
            self.env,
            learner.exploration_policy,
            frames_per_batch=int(cfg.frames_per_batch) * n,
            total_frames=int(cfg.frames) * n,
            init_random_frames=int(cfg.init_random_frames) * n,
        )
        steps = int(cfg.updates_per_batch)
        draws, per_draw = (steps, 1) if learner.update_draws_random else (min(steps, 1), steps)
        buffer = SeedReplayBuffer(int(cfg.buffer_size), num_seeds=n, device=learner.device)
        monitor = SeedsEarlyStop(cfg, [SeedRow(learner, i) for i in range(n)])
        counters = {"next_eval": first_evaluation(cfg) * n, "seconds": 0.0, "log": {}}
        logs = _SeedLogs(self.logs)
        state = loop_state(learner, buffer, collector, self.eval_env, monitor, counters)
        if (latest := resume_latest(self.checkpoints, state, logs)) is not None:
            log.info("stage %d (%s), %d seeds: resuming from %s", self.stage, self.name, n, latest)
        start = monitor.start = time.perf_counter() - counters["seconds"]
        watch = Stopwatch()
        value = learner.value(live=True)

        def learn(batch: TensorDictBase, frames: int) -> list[dict[str, torch.Tensor]]:
            with watch("collect"):
                if self.postproc is not None:
                    batch = self.postproc(batch)
                buffer.extend(batch.select(*self.keys, strict=False))
            per_seed = frames // n
            learner.anneal(per_seed)
            losses = []
            if per_seed >= cfg.init_random_frames:
                # only the seeds that have not stopped are sampled and updated: a stopped
                # seed's row gets no gradient (its stopped weights are restored at the end)
                active = monitor.active()
                rows = None if len(active) == n else torch.tensor(active, device=learner.device)
                for _ in range(draws):
                    with watch("sample"):
                        samples = buffer.sample(cfg.batch_size * per_draw, rows).split(
                            cfg.batch_size, dim=1
                        )
                    for sample in samples:
                        with watch("update"), update_rows(rows):
                            keep_threads()
                            losses.append(metrics_per_seed(learner.update(sample), rows, n))
                learner.check_finite()
            return losses

        def evaluate() -> tuple[list[float], list[float], list[float]]:
            frames = collector.frames // n
            max_steps = cfg.eval_max_steps or int(getattr(self.eval_env, "max_steps", 1000))
            summaries = evaluate_greedy_groups(
                self.eval_env,
                learner.policy,
                value,
                max_steps,
                self.gammas or float(cfg.gamma),
                cfg.value_error_reduce,
                groups=n,
            )
            for i in monitor.active():
                self.logs[i](
                    {f"eval/stage_{self.stage}/{k}": v for k, v in summaries[i].items()}, frames
                )
            return tuple(
                [s[k] for s in summaries]
                for k in ("success_rate", "value_error", "discounted_return")
            )

        class PerSeedFrames:  # run_loop's early stop gets the frames of each seed
            def record(self, model, success, value_error, frames, ret) -> bool:
                return monitor.record(learner.num_updates, success, value_error, frames // n, ret)

        try:
            run_loop(
                collector,
                learn=learn,
                log_batch=lambda batch, losses: self._log_batch(
                    batch, losses, collector.frames // n, monitor.active()
                ),
                evaluate=evaluate,
                early_stop=PerSeedFrames(),
                model=learner,
                eval_every=int(cfg.eval_every) * n,
                counters=counters,
                checkpoints=self.checkpoints,
                state=state,
                clock=(counters, start, logs),
                where=f"stage {self.stage} ({self.name})",
                watch=watch,
                progress=self.progress,
                count=lambda batch: collector.frames // n,
                open_ended=can_stop_early(cfg),
                seeds=self.seeds,
                training=monitor.active,
            )
        except (NonFiniteError, NonFiniteValueError) as err:
            bad = [
                s
                for s, row in zip(self.seeds, monitor.rows, strict=True)
                if not _finite(row.state_dict())
            ]
            where = f" (seeds {bad}: their weights are not finite)" if bad else ""
            cause = FloatingPointError(f"{err}{where}")
            raise DivergenceError(self.stage, self.name, learner, cause) from err
        seconds = time.perf_counter() - start
        out = []
        for i in range(n):
            at, early = monitor.stopped_at[i], monitor.monitors[i]
            restored = False
            if at is not None:
                monitor.rows[i].load_state_dict(at["state"])
            else:
                restored = early.restore_best(monitor.rows[i])
            success, value_error = early.final
            result = StageResult(
                self.stage,
                collector.frames // n if at is None else at["frames"],
                learner.num_updates if at is None else at["updates"],
                seconds if at is None else at["seconds"],
                success,
                value_error,
                early.stopped,
                restored,
                dict(watch.seconds),
                early.final_return,
            )
            plain = unstack_learner(learner, i, self.make_learner())
            plain.num_updates = result.updates
            out.append((plain, result))
        return out

    def _log_batch(
        self, batch: TensorDictBase, losses: list[dict], frames: int, active: list[int]
    ) -> None:
        if all(log.logger is None for log in self.logs):
            return
        parts = batch.reshape(self.n, -1)
        keys = dict.fromkeys(k for loss in losses for k in loss)
        means = {  # an entry some updates leave out (TD3's delayed actor loss): over the others
            k: torch.stack([loss[k] for loss in losses if k in loss]).mean(0).tolist() for k in keys
        }
        episodes = MetricsLog.episodes_by_row(parts)
        for i in active:
            metrics = {**episodes[i], **{k: v[i] for k, v in means.items()}}
            metrics["updates"] = self.learner.num_updates
            self.logs[i]({f"{self.prefix}/{k}": v for k, v in metrics.items()}, frames)


def finished_for_every_seed(
    stores: Sequence[Any], seeds: Sequence[int], stage: int, resume: str
) -> list[tuple[Learner, StageResult]] | None:
    """Each seed's finished ``stage`` (``store.finished(stage)``) when every seed's store has
    it, ``None`` when none has; a ``RuntimeError`` naming the seeds and the fix (``resume``: the
    command that resumes one seed's run directory) when only some have."""
    done = [store.finished(stage) if store is not None else None for store in stores]
    if all(d is None for d in done):
        return None
    missing = [s for s, d in zip(seeds, done, strict=True) if d is None]
    if missing:
        raise RuntimeError(
            f"stage {stage}: finished for some seeds but not for seeds {missing}; Fix: resume "
            f"those seeds' run directories one by one ({resume})"
        )
    return done


def start_stage_logs(
    stores: Sequence[Any], checkpoints: StageCheckpoints | None, stage: int
) -> None:
    """Without a checkpoint of ``stage`` to go on from, each seed's log is rewound to where
    the stage starts (``store.begin(stage)``: a resumed run drops the rows of the attempt that
    was interrupted)."""
    if checkpoints is None or checkpoints.latest() is None:
        for store in stores:
            if store is not None:
                store.begin(stage)


def seed_stacked_learner(
    make: Callable[..., Learner], seeds: Sequence[int], offset: int = 0
) -> Learner:
    """``make(seeds=len(seeds))`` holding, in row ``i``, the initial weights of
    ``make()`` built right after ``torch.manual_seed(seeds[i] + offset)`` (those of a single
    run with that seed)."""
    singles = []
    for seed in seeds:
        torch.manual_seed(seed + offset)
        singles.append(make())
    return stack_learners(make(seeds=len(seeds)), singles)


def train_and_keep(
    trainer: SeedsStageTrainer, stores: Sequence[Any]
) -> list[tuple[Learner, StageResult]]:
    """Trains ``trainer``'s stage; each seed's learner and result is kept in its store
    (``store.save``; a ``None`` store keeps nothing), then the stage's checkpoints, which the
    kept stage supersedes, are dropped. Returns each seed's learner and result."""
    out = trainer.train()
    for store, (learner, result) in zip(stores, out, strict=True):
        if store is not None:
            store.save(trainer.stage, learner, result)
    if trainer.checkpoints is not None:
        trainer.checkpoints.clear()
    return out
