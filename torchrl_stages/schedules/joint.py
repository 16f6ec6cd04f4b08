"""The paper's Algorithm 1: every stage learner keeps learning while the start region moves back.

Phase k (k = N-1, ..., 0) collects whole-task episodes that start inside stage k and run on
through the later stages with the stacked exploration policy of the *current* learners (one
collector over the whole-task env: per-stage collectors would end each episode at its stage's
exit). Every transition goes to the replay buffer of the stage of its state s_t. After each
collected batch, every stage with enough data takes its ``updates_per_batch`` gradient steps,
last stage first; a :class:`~torchrl_stages.transforms.StageRewardTransform` on stage m's buffer
gives the transitions that leave stage m their reward ``r + gamma_m V_{m+1}(s_{t+1})`` at
sampling time, from stage m+1's target networks as they are then (nothing is frozen). An env
that cannot start inside a chosen stage runs one phase from the task's own starts.

:class:`SeedsJointTrainer` is :class:`JointTrainer` with every
stage's learner seed-stacked (:mod:`~torchrl_stages.learners.stacking`), whole-task envs that
hold one copy of their batch per seed, and one
:class:`~torchrl_stages.replay.SeedReplayBuffer` per stage whose seeds fill at their own pace
(each transition goes to its seed's ring of the buffer of the stage of s_t). Each seed keeps
what a joint run of its own keeps: its initial weights (those of a single run with that seed),
its replay contents, the stages it updates (stage m of seed i takes its gradient steps once
seed i holds enough of stage m's transitions), its evaluations, each phase's early stop (a seed
that stops keeps the weights it stopped with and stores nothing more until the next phase),
its best weights, its phases and its metrics.

What the seeds share: the envs' random streams, each stage's exploration schedule (annealed by
the mean count of the updating seeds' transitions of that stage) and each parameter's Adam
step count. A seed's run is thus a draw from the distribution of a single run's, not its bits.
"""

from __future__ import annotations

import functools
import logging
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import Compose, RewardSum, TransformedEnv
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.collector import StageCollector
from torchrl_stages.evaluate import evaluate_greedy, evaluate_greedy_groups
from torchrl_stages.learners import Learner, make_learner
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
    run_loop,
)
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.replay import SeedReplayBuffer, stage_replay_buffer
from torchrl_stages.schedules.base import Schedule, StageStore, Trained, register_schedule
from torchrl_stages.seed_stage import (
    SeedsEarlyStop,
    TeamRow,
    _finite,
    _SeedLogs,
    finished_for_every_seed,
    metrics_per_seed,
    start_stage_logs,
)
from torchrl_stages.stage import DivergenceError, StageResult, stage_failure
from torchrl_stages.task import StagedTask, tile_starts
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import NonFiniteValueError, StageRewardTransform, StageTransform

log = logging.getLogger(__name__)

TAGS: tuple[NestedKey, ...] = (
    "stage",
    ("next", "stage"),
    ("next", "stage_transition"),
    ("next", "reward"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "done"),
)


class JointTrainer:
    """Trains all stage learners of ``task`` together (the paper's Algorithm 1).

    Phase k uses stage k's collection keys (``num_envs``, ``frames_per_batch``, ``frames`` as
    the phase budget, ``init_random_frames`` in the first phase) and its evaluation and
    early-stop keys; its evaluations are greedy whole-task episodes from stage-k starts (all of
    them when the env enumerates them), with the merged value ``V_stage(s_0)(s_0)`` checked
    against the merged discounted return. Each learner keeps its own ``batch_size``,
    ``buffer_size``, ``updates_per_batch``, schedules (counted in the transitions of its stage)
    and hyper-parameters. ``checkpoints`` makes the run resumable like the backward schedule.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> from torchrl_stages.task import StagedTask, tile_starts
        >>> tiny = DQNConfig(frames=512, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> learners, results, phases = JointTrainer(task).train()  # doctest: +SKIP
        >>> [p["start_stage"] for p in phases], [r.updates > 0 for r in results]  # doctest: +SKIP
        ([1, 0], [True, True])
    """

    def __init__(
        self,
        task: StagedTask,
        *,
        seed: int = 0,
        logger: Logger | None = None,
        progress: bool = False,
        checkpoints: StageCheckpoints | None = None,
        probe: Callable[[list[Learner], int], None] | None = None,
        compile: str = "off",
    ) -> None:
        self.task, self.seed, self.progress = task, seed, progress
        self.log = MetricsLog(logger)
        self.probe = probe
        self.checkpoints = checkpoints
        n = task.num_stages
        torch.manual_seed(seed)
        self.learners = [
            make_learner(task.stage_cfg(m), task.specs(m), compile, task.device) for m in range(n)
        ]
        self.gammas = [float(task.stage_cfg(m).gamma) for m in range(n)]
        self.buffers = [self._buffer(m) for m in range(n)]
        self.keys = [self._stored_keys(m, self.buffers[m].transform[0]) for m in range(n)]
        self.starts = list(reversed(range(n))) if task.stage_starts else [None]

    # ------------------------------------------------------------------ building blocks
    def _buffer(self, m: int) -> TensorDictReplayBuffer:
        cfg, n = self.task.stage_cfg(m), self.task.num_stages
        next_value = self.learners[m + 1].value(live=True) if m + 1 < n else None
        return stage_replay_buffer(
            cfg.buffer_size,
            self.learners[m].device,
            batch_size=int(cfg.batch_size),
            transform=StageRewardTransform(m, n, next_value=next_value, gamma=self.gammas[m]),
        )

    def _stored_keys(self, m: int, transform: StageRewardTransform) -> list[NestedKey]:
        """What stage m's buffer keeps: its loss's entries, the stage tags, and what the next
        stage's value (``transform``'s) reads from s_{t+1}."""
        keys = [*self.learners[m].replay_keys, *TAGS]
        if transform.next_value is not None:
            keys += [
                ("next", k) if isinstance(k, str) else ("next", *k)
                for k in transform.next_value.in_keys
            ]
        return list(dict.fromkeys(keys))

    #: copies of each env's batch (one per seed of seed-stacked learners)
    copies = 1

    def _env(self, start: int | None, batch_size: int, eval_env: bool = False):
        """Whole-task env from stage ``start``'s starts (tags only, no learner view), its batch
        repeated :attr:`copies` times."""
        task = self.task
        starts = task.start_states(start) if eval_env else None
        if starts is not None:
            base = task.base_env(**tile_starts(starts, self.copies))
        else:
            base = task.base_env(batch_size * self.copies, start_stage=start)
        tags = StageTransform(base.stage_fn, base.num_stages)
        return TransformedEnv(base, tags if eval_env else Compose(tags, RewardSum()))

    # ------------------------------------------------------------------ training
    def train(self) -> tuple[list[Learner], list[StageResult], list[dict[str, Any]]]:
        """Runs every phase; returns the learners, one result per stage and one per phase."""
        counters, seconds, watch = self._run_phases()
        results = [
            stage_result(m, counters["stored"][m], learner.num_updates, counters["phases"])
            for m, learner in enumerate(self.learners)
        ]
        for result in results:
            result.seconds, result.timing = seconds, dict(watch.seconds)
        return self.learners, results, counters["phases"]

    def _new_counters(self) -> dict[str, Any]:
        """The run's bookkeeping, saved with every checkpoint."""
        return {
            "phase": 0,
            "frames": 0,  # every phase's frames so far
            "stored": [0] * self.task.num_stages,
            "seconds": 0.0,
            "phases": [],
            "log": {},
            "in_phase": False,
        }

    def _run_phases(self) -> tuple[dict[str, Any], float, Stopwatch]:
        """Every phase from the newest checkpoint on; returns the counters, the seconds of
        training (every launch's) and where they went."""
        counters = self._new_counters()
        stateful = {
            "learners": StateOf(self._learner_states, self._load_learner_states),
            "counters": counters,
            **{f"replay_buffer_{m}": b for m, b in enumerate(self.buffers)},
        }
        latest = self.checkpoints.latest() if self.checkpoints is not None else None
        if latest is not None:
            self.checkpoints.load(latest, {"counters": counters})
        start = time.perf_counter() - counters["seconds"]
        watch = Stopwatch()
        for index in range(counters["phase"], len(self.starts)):
            counters["phase"] = index
            self._phase(self.starts[index], counters, stateful, latest, watch, start)
            latest = None
            counters.update(phase=index + 1, in_phase=False)
            if self.checkpoints is not None:  # a phase boundary: learners and buffers
                counters["seconds"] = time.perf_counter() - start
                counters["log"] = self.log.position()
                self.checkpoints.save(counters["frames"], stateful)
        return counters, time.perf_counter() - start, watch

    def _phase_envs(self, start_stage: int | None, cfg: DictConfig) -> tuple[Any, Any]:
        """The phase's training and evaluation envs, seeded as phase ``start_stage`` is
        (the global generator too)."""
        k = 0 if start_stage is None else start_stage
        torch.manual_seed(self.seed + 1000 * (k + 1))
        env = self._env(start_stage, int(cfg.num_envs))
        env.set_seed(self.seed + k)
        eval_env = self._env(start_stage, int(cfg.eval_episodes), eval_env=True)
        eval_env.set_seed(self.seed + 10_000 + k)
        return env, eval_env

    def _begin_phase(
        self,
        start_stage: int | None,
        counters: dict[str, Any],
        stateful: dict[str, Any],
        latest: Any,
        bookkeeping: Callable[[DictConfig], tuple[Any, dict[str, Any]]],
    ) -> tuple[int, DictConfig, StageCollector, Any, Any, dict[str, Any], dict[str, Any]]:
        """A phase's parts, restored from ``latest`` when the run resumes: its stage k and
        config, collector (:attr:`copies` times the config's batches), evaluation env, early
        stop and counters (``bookkeeping(cfg)``), and the state its checkpoints hold."""
        k = 0 if start_stage is None else start_stage
        cfg, copies = self.task.stage_cfg(k), self.copies
        resume_in_phase = latest is not None and counters["in_phase"]
        if latest is not None and not resume_in_phase:  # resumed at a phase boundary
            self.checkpoints.load(latest, stateful)
            self.log.rewind(counters["log"])
        env, eval_env = self._phase_envs(start_stage, cfg)
        first = counters["phase"] == 0
        collector = StageCollector(
            env,
            StackedPolicy(
                [learner.exploration_policy for learner in self.learners], skip_absent=False
            ),
            frames_per_batch=int(cfg.frames_per_batch) * copies,
            total_frames=int(cfg.frames) * copies,
            init_random_frames=int(cfg.init_random_frames) * copies if first else 0,
        )
        monitor, phase = bookkeeping(cfg)
        state = {
            **stateful,
            "collector": collector,
            "eval_env": eval_env.base_env,
            "monitor": monitor,
            "phase_counters": phase,
        }
        if resume_in_phase:
            self.checkpoints.load(latest, state)
            self.log.rewind(counters["log"])
        counters["in_phase"] = True
        return k, cfg, collector, eval_env, monitor, phase, state

    def _where(self, start_stage: int | None) -> str:
        """The phase from ``start_stage`` in messages, on its progress bar and in its log
        lines."""
        if start_stage is None:
            return "the joint phase from the task's own starts"
        return f"the joint phase from stage {start_stage} ({self.task.stage_names[start_stage]})"

    def _phase(self, start_stage, counters, stateful, latest, watch, t0) -> None:
        """One phase: collect from ``start_stage``'s starts, route, update every stage, evaluate."""
        k, cfg, collector, eval_env, monitor, phase, state = self._begin_phase(
            start_stage,
            counters,
            stateful,
            latest,
            lambda cfg: (EarlyStop(cfg), {"next_eval": first_evaluation(cfg)}),
        )
        team = nn.ModuleList(self.learners)  # the best evaluation keeps every learner's weights

        def count(batch: TensorDictBase) -> int:
            counters["frames"] += batch.numel()
            return counters["frames"]

        def learn(batch: TensorDictBase, frames: int) -> dict[int, list[dict]]:
            with watch("collect"):
                self._route(batch, counters["stored"])
            return self._update(counters["stored"], watch)

        def evaluate() -> tuple[float, float, float]:
            result = self.evaluate(k, eval_env, counters["frames"])
            if self.probe is not None and k == 0:
                self.probe(self.learners, counters["frames"])
            return result

        run_loop(
            collector,
            learn=learn,
            log_batch=lambda batch, losses: self._log_batch(k, batch, losses, counters["frames"]),
            evaluate=evaluate,
            early_stop=monitor,
            model=team,
            eval_every=int(cfg.eval_every),
            counters=phase,
            checkpoints=self.checkpoints,
            state=state,
            clock=(counters, t0, self.log),
            where=self._where(start_stage),
            watch=watch,
            progress=self.progress,
            count=count,
            open_ended=can_stop_early(cfg),
        )
        restored = monitor.restore_best(team)
        success, value_error = monitor.final
        counters["phases"].append(
            {
                "start_stage": start_stage,
                "frames": collector.frames,
                "success_rate": success,
                "value_error": value_error,
                "discounted_return": monitor.final_return,
                "early_stopped": monitor.stopped,
                "restored_best": restored,
            }
        )

    def _route(self, batch: TensorDictBase, stored: list[int]) -> None:
        """Each transition into the buffer of the stage of its state s_t."""
        flat = batch.reshape(-1)
        stage = flat.get("stage").reshape(-1)
        for m, buffer in enumerate(self.buffers):
            rows = stage == m
            count = int(rows.sum())
            if count:
                buffer.extend(flat[rows].select(*self.keys[m], strict=False))
                stored[m] += count

    def _update(self, stored: list[int], watch: Stopwatch) -> dict[int, list[dict]]:
        """Every stage with enough data takes its gradient steps, the last stage first."""
        losses: dict[int, list[dict]] = {}
        for m in reversed(range(self.task.num_stages)):
            cfg, learner = self.task.stage_cfg(m), self.learners[m]
            if stored[m] < max(int(cfg.init_random_frames), int(cfg.batch_size), 1):
                continue
            learner.anneal(stored[m])
            losses[m] = []
            try:
                for _ in range(int(cfg.updates_per_batch)):
                    with watch("sample"):
                        sample = self.buffers[m].sample()  # stage m's view, computed now
                    with watch("update"):
                        keep_threads()
                        losses[m].append(learner.update(sample))
                learner.check_finite()
            except (NonFiniteError, NonFiniteValueError) as err:
                name = self.task.stage_names[m]
                raise stage_failure(err, m, name, learner, self.buffers[m]) from err
        return losses

    @functools.cached_property
    def _value(self) -> StackedPolicy:
        """What evaluations read V from: every stage's target networks themselves (live), built
        once instead of copied at every evaluation."""
        return StackedPolicy([learner.value(live=True) for learner in self.learners])

    @torch.no_grad()
    def evaluate(self, k: int, eval_env, frames: int) -> tuple[float, float, float]:
        """Greedy whole-task episodes from stage-k starts: success, merged value error and
        merged discounted return (logged under ``eval/joint_<k>/``)."""
        cfg = self.task.stage_cfg(k)
        policy = StackedPolicy([learner.policy for learner in self.learners])
        max_steps = int(getattr(eval_env.base_env, "max_steps", 1000))
        if cfg.eval_max_steps:  # each stage an episode crosses may take eval_max_steps
            max_steps = min(max_steps, int(cfg.eval_max_steps) * (self.task.num_stages - k))
        summary = evaluate_greedy(
            eval_env, policy, self._value, max_steps, self.gammas, cfg.value_error_reduce
        )
        self.log({f"eval/joint_{k}/{key}": v for key, v in summary.items()}, frames)
        return summary["success_rate"], summary["value_error"], summary["discounted_return"]

    # ------------------------------------------------------------------ state and logs
    def _learner_states(self) -> list[dict]:
        return [learner.checkpoint() for learner in self.learners]

    def _load_learner_states(self, states: Sequence[dict]) -> None:
        for learner, state in zip(self.learners, states, strict=True):
            learner.load_checkpoint(state)

    def _log_batch(self, k: int, batch, losses: dict[int, list[dict]], frames: int) -> None:
        if self.log.logger is None:
            return
        metrics = {f"train/joint_{k}/{key}": v for key, v in MetricsLog.episodes(batch).items()}
        for m, stage_losses in losses.items():
            for key, value in MetricsLog.losses(stage_losses).items():
                metrics[f"train/stage_{m}/{key}"] = value
            metrics[f"train/stage_{m}/updates"] = self.learners[m].num_updates
        self.log(metrics, frames)


class SeedsJointTrainer(JointTrainer):
    """Trains every stage learner of ``task`` together (the joint schedule) for every seed of
    ``seeds`` at once; :meth:`train` returns one :class:`~torchrl_stages.schedules.Trained` per
    seed (ordinary learners, results and phases).

    A phase's keys are per seed, as in :class:`~torchrl_stages.schedules.joint.JointTrainer`
    (``frames`` is each seed's phase budget). ``logs`` (one per seed) receive each seed's
    metrics under the keys a single joint run logs; with ``checkpoints`` the run saves the state
    of every seed together and goes on from the newest one, the seeds' logs rewound with it.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> tiny = DQNConfig(frames=512, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> task = StagedTask(OmegaConf.create({
        ...     "name": "grid", "stages": {"a": tiny, "b": tiny},
        ...     "env": {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10,
        ...             "num_stages": 2},
        ... }))
        >>> runs = SeedsJointTrainer(task, [0, 1]).train()  # doctest: +SKIP
        >>> [[p["start_stage"] for p in run.extra["phases"]] for run in runs]  # doctest: +SKIP
        [[1, 0], [1, 0]]
    """

    def __init__(
        self,
        task: StagedTask,
        seeds: Sequence[int],
        *,
        logs: Sequence[MetricsLog] | None = None,
        progress: bool = False,
        checkpoints: StageCheckpoints | None = None,
    ) -> None:
        self.task, self.progress, self.checkpoints = task, progress, checkpoints
        self.seeds = list(seeds)
        n = self.copies = len(self.seeds)
        self.seed, self.probe = self.seeds[0], None  # the envs' streams are the first seed's
        self.logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
        if len(self.logs) != n:
            raise ValueError(f"{len(self.logs)} logs for {n} seeds")
        self.log = _SeedLogs(self.logs)
        stages = task.num_stages
        self.learners = self._stacked_learners()
        self.gammas = [float(task.stage_cfg(m).gamma) for m in range(stages)]
        self.transforms = [
            StageRewardTransform(
                m,
                stages,
                next_value=self.learners[m + 1].value(live=True) if m + 1 < stages else None,
                gamma=self.gammas[m],
            )
            for m in range(stages)
        ]
        self.buffers = [
            SeedReplayBuffer(
                int(task.stage_cfg(m).buffer_size), num_seeds=n, device=self.learners[m].device
            )
            for m in range(stages)
        ]
        self.keys = [self._stored_keys(m, self.transforms[m]) for m in range(stages)]
        self.starts = list(reversed(range(stages))) if task.stage_starts else [None]

    def _plain(self, m: int, seeds: int | None = None) -> Learner:
        return make_learner(
            self.task.stage_cfg(m), self.task.specs(m), device=self.task.device, seeds=seeds
        )

    def _stacked_learners(self) -> list[Learner]:
        """Stage m's learner stacked for the seeds, row i holding the initial weights of a
        joint run with seed ``seeds[i]`` (its generator seeded, then stages 0..N-1 built)."""
        stages = range(self.task.num_stages)
        singles = []
        for seed in self.seeds:
            torch.manual_seed(seed)
            singles.append([self._plain(m) for m in stages])
        return [
            stack_learners(self._plain(m, len(self.seeds)), [one[m] for one in singles])
            for m in stages
        ]

    # ------------------------------------------------------------------ training
    def train(self) -> list[Trained]:  # type: ignore[override]
        counters, seconds, watch = self._run_phases()
        out = []
        for i in range(len(self.seeds)):
            phases = counters["phases"][i]
            learners, results = [], []
            for m, stacked in enumerate(self.learners):
                learner = unstack_learner(stacked, i, self._plain(m))
                learner.num_updates = counters["updates"][i][m]
                learners.append(learner)
                result = stage_result(m, counters["stored"][i][m], learner.num_updates, phases)
                result.seconds, result.timing = seconds, dict(watch.seconds)
                results.append(result)
            out.append(Trained(learners, results, {"phases": phases}))
        return out

    def _new_counters(self) -> dict[str, Any]:
        n, stages = len(self.seeds), self.task.num_stages
        return {
            "phase": 0,
            "frames": 0,  # every phase's frames so far, per seed (the checkpoints' names)
            "trained": [0] * n,  # each seed's frames while it trained (its metrics' x axis)
            "stored": [[0] * stages for _ in range(n)],  # per seed and stage
            "updates": [[0] * stages for _ in range(n)],
            "seconds": 0.0,
            "phases": [[] for _ in range(n)],  # per seed
            "log": {},
            "in_phase": False,
        }

    def _phase(self, start_stage, counters, stateful, latest, watch, t0) -> None:
        """One phase for every seed: collect from ``start_stage``'s starts, route each seed's
        transitions, update each seed's ready stages, evaluate each seed, stop each seed."""
        n = len(self.seeds)
        rows = [TeamRow(self.learners, i) for i in range(n)]
        k, cfg, collector, eval_env, monitor, phase, state = self._begin_phase(
            start_stage,
            counters,
            stateful,
            latest,
            lambda cfg: (
                SeedsEarlyStop(cfg, rows, start=t0),
                {"next_eval": first_evaluation(cfg) * n, "frames": [0] * n},
            ),
        )

        def count(batch: TensorDictBase) -> int:
            counters["frames"] += batch.numel() // n
            return counters["frames"]

        def learn(batch: TensorDictBase, frames: int) -> dict[int, list[dict]]:
            active = monitor.active()
            with watch("collect"):
                self._route_seeds(batch, active, counters, phase["frames"])
            return self._update_seeds(active, counters, watch)

        def evaluate() -> tuple[list[float], list[float], list[float]]:
            summaries = self.evaluate_seeds(k, eval_env, monitor.active(), counters["trained"])
            return tuple(
                [s[key] for s in summaries]
                for key in ("success_rate", "value_error", "discounted_return")
            )

        learners = self.learners

        class PerSeed:  # run_loop's early stop gets each seed's frames and updates
            def record(self, model, success, value_error, frames, ret) -> bool:
                training = set(monitor.active())
                updates = [sum(u) for u in counters["updates"]]
                done = monitor.record(updates, success, value_error, phase["frames"], ret)
                for i in training.difference(monitor.active()):  # its optimizers' state too
                    monitor.stopped_at[i]["moments"] = seed_moments(learners, i)
                return done

        run_loop(
            collector,
            learn=learn,
            log_batch=lambda batch, losses: self._log_seeds(
                k, batch, losses, counters["trained"], monitor.active(), counters["updates"]
            ),
            evaluate=evaluate,
            early_stop=PerSeed(),
            model=None,
            eval_every=int(cfg.eval_every) * n,
            counters=phase,
            checkpoints=self.checkpoints,
            state=state,
            clock=(counters, t0, self.log),
            where=self._where(start_stage),
            watch=watch,
            progress=self.progress,
            count=count,
            open_ended=can_stop_early(cfg),
            seeds=self.seeds,
            training=monitor.active,
        )
        for i, (row, early) in enumerate(zip(rows, monitor.monitors, strict=True)):
            at, restored = monitor.stopped_at[i], False
            if at is not None:  # the weights it stopped with (the others trained on), and
                row.load_state_dict(at["state"])  # its Adam moments, which decayed meanwhile
                seed_moments(self.learners, i, load=at.get("moments", {}))
            else:
                restored = early.restore_best(row)
            success, value_error = early.final
            counters["phases"][i].append(
                {
                    "start_stage": start_stage,
                    "frames": phase["frames"][i],
                    "success_rate": success,
                    "value_error": value_error,
                    "discounted_return": early.final_return,
                    "early_stopped": early.stopped,
                    "restored_best": restored,
                }
            )

    def _route_seeds(
        self,
        batch: TensorDictBase,
        active: list[int],
        counters: dict[str, Any],
        frames: list[int],
    ) -> None:
        """Each transition of a seed still training into its seed's ring of the buffer of
        the stage of its state s_t (a stopped seed's are dropped), counted in its stage's
        ``stored``, its phase's ``frames`` and its run's ``trained`` frames."""
        stored = counters["stored"]
        n = len(self.seeds)
        parts = batch.reshape(n, -1)  # seed-major
        stage = parts.get("stage").reshape(n, -1)
        training = torch.zeros(n, dtype=torch.bool, device=stage.device)
        training[active] = True
        owner = torch.arange(n, device=stage.device).unsqueeze(1).expand_as(stage)
        for m, buffer in enumerate(self.buffers):
            rows = (stage == m) & training.unsqueeze(1)
            added = rows.sum(1).tolist()
            if any(added):
                buffer.extend(parts[rows].select(*self.keys[m], strict=False), seeds=owner[rows])
                for i, count in enumerate(added):
                    stored[i][m] += count
        for i in active:
            frames[i] += parts.shape[1]
            counters["trained"][i] += parts.shape[1]

    def _update_seeds(
        self, active: list[int], counters: dict[str, Any], watch: Stopwatch
    ) -> dict[int, list[dict]]:
        """Every stage takes its gradient steps, the last stage first, for the seeds still
        training that hold enough of its transitions (the others' rows are left out)."""
        n, stored = len(self.seeds), counters["stored"]
        losses: dict[int, list[dict]] = {}
        for m in reversed(range(self.task.num_stages)):
            cfg, learner = self.task.stage_cfg(m), self.learners[m]
            need = max(int(cfg.init_random_frames), int(cfg.batch_size), 1)
            ready = [i for i in active if stored[i][m] >= need]
            if not ready:
                continue
            learner.anneal(round(statistics.mean(stored[i][m] for i in ready)))
            rows = None if len(ready) == n else torch.tensor(ready, device=learner.device)
            steps, size = int(cfg.updates_per_batch), int(cfg.batch_size)
            draws, per_draw = (steps, 1) if learner.update_draws_random else (min(steps, 1), steps)
            losses[m] = []
            try:
                for _ in range(draws):
                    with watch("sample"), update_rows(rows):  # stage m's view, computed now
                        drawn = self.transforms[m](self.buffers[m].sample(size * per_draw, rows))
                    for sample in drawn.split(size, dim=1):
                        with watch("update"), update_rows(rows):
                            keep_threads()
                            losses[m].append(metrics_per_seed(learner.update(sample), rows, n))
                learner.check_finite()
            except (NonFiniteError, NonFiniteValueError) as err:
                rows_of = [TeamRow(self.learners, i) for i in ready]
                bad = [
                    self.seeds[i]
                    for i, row in zip(ready, rows_of, strict=True)
                    if not _finite(row.state_dict())
                ]
                where = f" (seeds {bad}: their weights are not finite)" if bad else ""
                cause = FloatingPointError(f"{err}{where}")
                raise DivergenceError(m, self.task.stage_names[m], learner, cause) from err
            for i in ready:
                counters["updates"][i][m] += steps
        return losses

    @torch.no_grad()
    def evaluate_seeds(
        self, k: int, eval_env, active: Sequence[int], frames: Sequence[int]
    ) -> list[dict[str, float]]:
        """Greedy whole-task episodes from stage-k starts, one summary per seed (the seeds
        still training log theirs under ``eval/joint_<k>/``)."""
        cfg = self.task.stage_cfg(k)
        policy = StackedPolicy([learner.policy for learner in self.learners])
        max_steps = int(getattr(eval_env.base_env, "max_steps", 1000))
        if cfg.eval_max_steps:
            max_steps = min(max_steps, int(cfg.eval_max_steps) * (self.task.num_stages - k))
        summaries = evaluate_greedy_groups(
            eval_env,
            policy,
            self._value,
            max_steps,
            self.gammas,
            cfg.value_error_reduce,
            groups=len(self.seeds),
        )
        for i in active:
            self.logs[i]({f"eval/joint_{k}/{key}": v for key, v in summaries[i].items()}, frames[i])
        return summaries

    def _log_seeds(
        self,
        k: int,
        batch: TensorDictBase,
        losses: dict[int, list[dict]],
        frames: Sequence[int],
        active: Sequence[int],
        updates: Sequence[Sequence[int]],
    ) -> None:
        if all(one.logger is None for one in self.logs):
            return
        n = len(self.seeds)
        episodes = MetricsLog.episodes_by_row(batch.reshape(n, -1))
        means: dict[int, dict[str, list[float]]] = {}
        for m, stage_losses in losses.items():
            keys = dict.fromkeys(key for loss in stage_losses for key in loss)
            means[m] = {
                key: torch.stack([loss[key] for loss in stage_losses if key in loss])
                .mean(0)
                .tolist()
                for key in keys
            }
        for i in active:
            metrics = {f"train/joint_{k}/{key}": v for key, v in episodes[i].items()}
            for m, stage_means in means.items():
                values = {key: v[i] for key, v in stage_means.items()}
                if all(v != v for v in values.values()):  # NaN: seed i's stage m waits for data
                    continue
                for key, value in values.items():
                    metrics[f"train/stage_{m}/{key}"] = value
                metrics[f"train/stage_{m}/updates"] = updates[i][m]
            self.logs[i](metrics, frames[i])


def seed_moments(
    learners: Sequence[Learner], seed: int, load: dict[str, torch.Tensor] | None = None
) -> dict[str, torch.Tensor]:
    """Seed ``seed``'s rows of the Adam moments (``exp_avg``, ``exp_avg_sq``) of every
    optimizer of the seed-stacked ``learners``, copied out; with ``load`` (what this returned)
    written back instead. A seed that stops while the others train on is left out of their
    updates, but Adam still decays its moments at every step; written back, the seed goes on
    in the next phase from the optimizer state it stopped with, as a run of its own would."""
    out: dict[str, torch.Tensor] = {}
    for m, learner in enumerate(learners):
        names = {id(p): n for n, p in learner.named_parameters(remove_duplicate=False)}
        axes = seed_axes(learner)
        for optimizer_name, optimizer in learner.optimizers.items():
            for group in optimizer.param_groups:
                for param in group["params"]:
                    name = names.get(id(param), "")
                    axis, state = axes.get(name), optimizer.state.get(param, {})
                    for key in ("exp_avg", "exp_avg_sq"):
                        if axis is None or key not in state:
                            continue
                        entry = f"{m}.{optimizer_name}.{name}.{key}"
                        if load is None:
                            out[entry] = state[key].select(axis, seed).clone()
                        elif entry in load:
                            state[key].select(axis, seed).copy_(load[entry])
    return out


def train_joint_seeds(
    task: StagedTask,
    seeds: Sequence[int],
    *,
    stores: Sequence[StageStore | None] | None = None,
    logs: Sequence[MetricsLog] | None = None,
    progress: bool = False,
    checkpoints: Any = None,
) -> list[Trained]:
    """The joint schedule for every seed of ``seeds`` at once (:class:`SeedsJointTrainer`);
    ``stores``, ``logs`` and ``checkpoints`` (called with ``"joint"``) as in
    :func:`~torchrl_stages.schedules.backward.train_backward_seeds`. A run every seed's store
    has finished is loaded, not trained."""
    n, stages = len(seeds), task.num_stages
    stores = list(stores) if stores is not None else [None] * n
    resume = "stages-train schedule=joint seed=<s> resume=true hydra.run.dir=<its directory>"
    done = [finished_for_every_seed(stores, seeds, k, resume) for k in range(stages)]
    if all(d is not None for d in done):
        return [
            Trained(
                [done[k][i][0] for k in range(stages)],
                [done[k][i][1] for k in range(stages)],
                {"phases": list(stores[i].kept("phases") or [])},
            )
            for i in range(n)
        ]
    scope = checkpoints("joint") if checkpoints is not None else None
    start_stage_logs(stores, scope, "joint")
    trainer = SeedsJointTrainer(task, seeds, logs=logs, progress=progress, checkpoints=scope)
    runs = trainer.train()
    for seed, store, run in zip(seeds, stores, runs, strict=True):
        log_phases(run.extra["phases"], f"seed {seed}: joint")
        if store is not None:
            keep_joint(store, run.learners, run.results, run.extra["phases"])
    if scope is not None:
        scope.clear()
    return runs


@register_schedule
class JointSchedule(Schedule):
    """``schedule=joint`` (:class:`JointTrainer`): every stage trains at once, so the run
    resumes as a whole (checkpoints ``"joint"``) and its stage files are written when it ends;
    its phases, not its stages, stop early."""

    name = "joint"
    stage_early_stop = False
    stacks_seeds = True

    def checkpoint_scope(self, stage: int) -> str:
        return "joint"

    def train(self, task: StagedTask, store: StageStore | None = None, **kwargs) -> Trained:
        n = task.num_stages
        if store is not None:  # a finished run resumed: its stages and phases as they were
            done = [store.finished(k) for k in range(n)]
            if all(d is not None for d in done):
                phases = list(store.kept("phases") or [])
                return Trained([d[0] for d in done], [d[1] for d in done], {"phases": phases})
        checkpoints = store.begin("joint") if store is not None else None
        learners, results, phases = JointTrainer(task, checkpoints=checkpoints, **kwargs).train()
        log_phases(phases)
        if store is not None:
            keep_joint(store, learners, results, phases)
        return Trained(learners, results, {"phases": phases})

    def train_seeds(self, task: StagedTask, seeds: Sequence[int], **kwargs) -> list[Trained]:
        return train_joint_seeds(task, seeds, **kwargs)


def stage_result(
    stage: int, stored: int, updates: int, phases: Sequence[dict[str, Any]]
) -> StageResult:
    """Stage ``stage``'s result in a joint run: the transitions of it that were stored, its
    updates and the last phase's whole-task evaluation (the caller sets ``seconds`` and
    ``timing``, the run's)."""
    last = phases[-1] if phases else {}
    return StageResult(
        stage,
        stored,
        updates,
        0.0,
        last.get("success_rate"),
        last.get("value_error"),
        bool(last.get("early_stopped", False)),
        bool(last.get("restored_best", False)),
        discounted_return=last.get("discounted_return"),
    )


def log_phases(phases: Sequence[dict[str, Any]], who: str = "joint") -> None:
    """One line per phase: where it started, its frames, its whole-task evaluation."""
    for phase in phases:
        start = phase["start_stage"]
        log.info(
            "%s phase from %s: %d frames, whole-task success %.2f, value error %.3f%s",
            who,
            "the task's own starts" if start is None else f"stage {start} starts",
            phase["frames"],
            phase["success_rate"] if phase["success_rate"] is not None else float("nan"),
            phase["value_error"] if phase["value_error"] is not None else float("nan"),
            " (early stop)" if phase["early_stopped"] else " (budget used, best restored)",
        )


def keep_joint(
    store: StageStore,
    learners: Sequence[Learner],
    results: Sequence[StageResult],
    phases: Sequence[dict[str, Any]],
) -> None:
    """Keeps a finished joint run in ``store``: its phases (for a resumed launch's
    ``eval.json``) and every stage; its checkpoints go."""
    store.keep("phases", list(phases))
    for k, (learner, result) in enumerate(zip(learners, results, strict=True)):
        store.save(k, learner, result)
    store.clear("joint")
