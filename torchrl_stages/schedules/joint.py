"""The paper's Algorithm 1: every stage learner keeps learning while the start region moves back.

Phase k (k = N-1, ..., 0) collects whole-task episodes that start inside stage k and run on
through the later stages with the stacked exploration policy of the *current* learners (one
collector over the whole-task env: per-stage collectors would end each episode at its stage's
exit). Every transition goes to the replay buffer of the stage of its state s_t. After each
collected batch, every stage with enough data takes its ``updates_per_batch`` gradient steps,
last stage first; a :class:`~torchrl_stages.transforms.StageRewardTransform` gives the sampled
transitions that leave stage m their reward ``r + gamma_m V_{m+1}(s_{t+1})``, from stage m+1's
target networks as they are then (nothing is frozen). An env that cannot start inside a chosen
stage runs one phase from the task's own starts.

Several seeds train at once as for a backward stage (:mod:`~torchrl_stages.stage`): every
stage's learner seed-stacked, whole-task envs holding one copy of their batch per seed, and
one :class:`~torchrl_stages.replay.SeedReplayBuffer` per stage whose seeds fill at their own
pace. Each seed keeps what a joint run of its own keeps: its initial weights, its replay
contents, the stages it updates (stage m of seed i takes its gradient steps once seed i holds
enough of stage m's transitions), its evaluations, each phase's early stop (a seed that stops
keeps the weights and Adam moments it stopped with and keepers nothing more until the next
phase), its best weights, its phases and its metrics. What the seeds share: the envs' random
streams, each stage's exploration schedule (annealed by the mean count of the updating seeds'
transitions of that stage) and each parameter's Adam step count.
"""

from __future__ import annotations

import functools
import logging
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs import Compose, RewardSum, TransformedEnv

from torchrl_stages.checkpoint import (
    CHECKPOINT_FORMAT,
    SavedCounters,
    StageCheckpoints,
    StateOf,
)
from torchrl_stages.collector import StageCollector
from torchrl_stages.early_stop import (
    Evaluation,
    SeedEarlyStops,
    TeamRow,
    first_evaluation,
)
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.failures import stage_failure
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.learners.stacking import (
    seed_axes,
    stack_learners,
    unstack_learner,
    update_rows,
)
from torchrl_stages.loop import LoopCounters, Stopwatch, Trainer, can_stop_early
from torchrl_stages.metric_names import STAGE, metric_name
from torchrl_stages.metrics import MetricsLog, SeedLogs
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.schedules.base import (
    Probe,
    Schedule,
    StageKeeper,
    Trained,
    begin_loop,
    finished_for_every_seed,
    register_schedule,
)
from torchrl_stages.seeding import EVAL_OFFSET, phase_seed, stage_seed
from torchrl_stages.stage import StageResult, loss_means, per_seed_metrics
from torchrl_stages.task import StagedTask, tile_starts
from torchrl_stages.threads import keep_threads
from torchrl_stages.transforms import NonFiniteValueError, StageRewardTransform, StageTransform

log = logging.getLogger(__name__)

#: the metrics scope of the phases (``eval/joint_<k>/...``: the phase from stage k)
JOINT = "joint"

TAGS: tuple[NestedKey, ...] = (
    "stage",
    ("next", "stage"),
    ("next", "stage_transition"),
    ("next", "reward"),
    ("next", "terminated"),
    ("next", "truncated"),
    ("next", "done"),
)


@dataclass
class JointCounters(SavedCounters):
    """What a joint run counts, per seed where seeds differ, saved with its checkpoints."""

    stages: int
    seeds: int
    phase: int = 0  # the phase in progress
    frames: int = 0  # every phase's frames so far, per seed (the checkpoints' names)
    in_phase: bool = False  # whether the newest checkpoint is inside a phase
    seconds: float = 0.0
    log: dict[str, Any] = field(default_factory=dict)
    trained: list[int] = field(default_factory=list)  # each seed's frames while it trained
    phase_frames: list[int] = field(default_factory=list)  # ... in the phase in progress
    stored: list[list[int]] = field(default_factory=list)  # per seed and stage
    updates: list[list[int]] = field(default_factory=list)  # per seed and stage
    phases: list[list[dict[str, Any]]] = field(default_factory=list)  # per seed
    format: int = CHECKPOINT_FORMAT  # what a resumed run checks first

    def __post_init__(self) -> None:
        n, stages = self.seeds, self.stages
        self.trained = self.trained or [0] * n
        self.phase_frames = self.phase_frames or [0] * n
        self.stored = self.stored or [[0] * stages for _ in range(n)]
        self.updates = self.updates or [[0] * stages for _ in range(n)]
        self.phases = self.phases or [[] for _ in range(n)]


def team_rows(learners: Sequence[Learner]) -> list[Any]:
    """What a whole-task early stop keeps and restores of each seed: every stage's learner
    (ordinary learners: the team itself, one row), or each seed's :class:`TeamRow`."""
    if learners[0].seeds is None:
        return [nn.ModuleList(learners)]
    return [TeamRow(learners, i) for i in range(int(learners[0].seeds))]


class JointTrainer:
    """Trains all stage learners of ``task`` together (the paper's Algorithm 1), for every seed
    of ``seeds`` at once; :meth:`train` returns one :class:`~torchrl_stages.schedules.Trained`
    per seed (ordinary learners, results and phases).

    Phase k uses stage k's collection keys (``num_envs``, ``frames_per_batch``, ``frames`` as
    the phase budget per seed, ``init_random_frames`` in the first phase) and its evaluation
    and early-stop keys; its evaluations are greedy whole-task episodes from stage-k starts
    (all of them when the env enumerates them), with the merged value ``V_stage(s_0)(s_0)``
    checked against the merged discounted return. Each learner keeps its own ``batch_size``,
    ``buffer_size``, ``updates_per_batch``, schedules (counted in the transitions of its stage)
    and hyper-parameters. ``logs`` (one per seed) receive each seed's metrics; ``checkpoints``
    makes the run resumable like the backward schedule; ``probe`` (one seed) follows the whole
    task at the evaluations of the phase from stage 0.

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
        >>> runs = JointTrainer(task, [0, 1]).train()  # doctest: +SKIP
        >>> [[p["start_stage"] for p in run.extra["phases"]] for run in runs]  # doctest: +SKIP
        [[1, 0], [1, 0]]
    """

    def __init__(
        self,
        task: StagedTask,
        seeds: Sequence[int] = (0,),
        *,
        logs: Sequence[MetricsLog] | None = None,
        progress: bool = False,
        checkpoints: StageCheckpoints | None = None,
        probe: Probe | None = None,
        compile: str = "off",
    ) -> None:
        self.task, self.progress, self.checkpoints, self.probe = task, progress, checkpoints, probe
        self.seeds = list(seeds)
        n = self.n = len(self.seeds)
        logs = list(logs) if logs is not None else [MetricsLog(None) for _ in range(n)]
        if len(logs) != n:
            raise ValueError(f"{len(logs)} logs for {n} seeds")
        self.logs = SeedLogs(logs)
        stages = task.num_stages
        self.make = [
            functools.partial(make_learner, task.stage_cfg(m), task.specs(m), compile, task.device)
            for m in range(stages)
        ]
        self.learners = self._seeded_learners()
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

    # ------------------------------------------------------------------ building blocks
    def _seeded_learners(self) -> list[Learner]:
        """Every stage's learner, built right after ``torch.manual_seed(seed)`` (several seeds:
        stacked, row i holding what a joint run of ``seeds[i]`` starts from)."""
        stages = range(self.task.num_stages)
        if self.n == 1:
            torch.manual_seed(self.seeds[0])
            return [self.make[m]() for m in stages]
        rows: list[list[Learner]] = [[] for _ in stages]
        for seed in self.seeds:  # each seed's generator builds its stages 0..N-1 in turn
            torch.manual_seed(seed)
            for m in stages:
                rows[m].append(self.make[m]())
        return [stack_learners(self.make[m](seeds=self.n), rows[m]) for m in stages]

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

    def _env(self, start: int | None, batch_size: int, eval_env: bool = False):
        """Whole-task env from stage ``start``'s starts (tags only, no learner view), its batch
        repeated once per seed."""
        task = self.task
        starts = task.start_states(start) if eval_env else None
        if starts is not None:
            base = task.base_env(**tile_starts(starts, self.n))
        else:
            base = task.base_env(batch_size * self.n, start_stage=start)
        tags = StageTransform(base.stage_fn, base.num_stages)
        return TransformedEnv(base, tags if eval_env else Compose(tags, RewardSum()))

    def _phase_envs(self, k: int, start_stage: int | None, cfg) -> tuple[Any, Any]:
        """The phase's training and evaluation envs, seeded as phase ``k`` is (the global
        generator too: :mod:`~torchrl_stages.seeding`)."""
        seed = self.seeds[0]
        torch.manual_seed(phase_seed(seed, k))
        env = self._env(start_stage, int(cfg.num_envs))
        env.set_seed(stage_seed(seed, k))
        eval_env = self._env(start_stage, int(cfg.eval_episodes), eval_env=True)
        eval_env.set_seed(stage_seed(seed, k) + EVAL_OFFSET)
        return env, eval_env

    @functools.cached_property
    def _value(self) -> StackedPolicy:
        """What evaluations read V from: every stage's target networks themselves (live), built
        once instead of copied at every evaluation."""
        return StackedPolicy([learner.value(live=True) for learner in self.learners])

    # ------------------------------------------------------------------ training
    def train(self) -> list[Trained]:
        """Runs every phase; returns each seed's learners, one result per stage and its
        phases."""
        counters, seconds, watch = self._run_phases()
        out = []
        for i in range(self.n):
            phases = counters.phases[i]
            learners, results = [], []
            for m, learner in enumerate(self.learners):
                if learner.seeds is not None:
                    learner = unstack_learner(learner, i, self.make[m]())
                learner.num_updates = counters.updates[i][m]
                learners.append(learner)
                result = stage_result(m, counters.stored[i][m], learner.num_updates, phases)
                result.seconds, result.timing = seconds, dict(watch.seconds)
                results.append(result)
            out.append(Trained(learners, results, {"phases": phases}))
        return out

    def _run_phases(self) -> tuple[JointCounters, float, Stopwatch]:
        """Every phase from the newest checkpoint on; returns the counters, the seconds of
        training (every launch's) and where they went."""
        counters = JointCounters(self.task.num_stages, self.n)
        stateful = {
            "learners": StateOf(self._learner_states, self._load_learner_states),
            "counters": counters,
            **{f"replay_buffer_{m}": b for m, b in enumerate(self.buffers)},
        }
        latest = self.checkpoints.latest() if self.checkpoints is not None else None
        if latest is not None:
            self.checkpoints.load(latest, {"counters": counters})
            seeds = f", {self.n} seeds" if self.n > 1 else ""
            log.info("joint%s: resuming from %s", seeds, latest)
        start = time.perf_counter() - counters.seconds
        watch = Stopwatch()
        for index in range(counters.phase, len(self.starts)):
            counters.phase = index
            self._phase(self.starts[index], counters, stateful, latest, watch, start)
            latest = None
            counters.phase, counters.in_phase = index + 1, False
            if self.checkpoints is not None:  # a phase boundary: learners and buffers
                counters.seconds = time.perf_counter() - start
                counters.log = self.logs.position()
                self.checkpoints.save(counters.frames, stateful)
        return counters, time.perf_counter() - start, watch

    def _phase(self, start_stage, counters: JointCounters, stateful, latest, watch, t0) -> None:
        """One phase for every seed: collect from ``start_stage``'s starts, route each seed's
        transitions, update each seed's ready stages, evaluate each seed, stop each seed."""
        n, k = self.n, 0 if start_stage is None else start_stage
        cfg = self.task.stage_cfg(k)
        resume_in_phase = latest is not None and counters.in_phase
        if latest is not None and not resume_in_phase:  # resumed at a phase boundary
            self.checkpoints.load(latest, stateful)
            self.logs.rewind(counters.log)
        env, eval_env = self._phase_envs(k, start_stage, cfg)
        first = counters.phase == 0
        collector = StageCollector(
            env,
            StackedPolicy(
                [learner.exploration_policy for learner in self.learners], skip_absent=False
            ),
            frames_per_batch=int(cfg.frames_per_batch) * n,
            total_frames=int(cfg.frames) * n,
            init_random_frames=int(cfg.init_random_frames) * n if first else 0,
        )
        stops = SeedEarlyStops(cfg, team_rows(self.learners), start=t0)
        phase = LoopCounters(next_eval=first_evaluation(cfg))
        state = {
            **stateful,
            "collector": collector,
            "eval_env": eval_env.base_env,
            "monitor": stops,
            "phase_counters": phase,
        }
        if resume_in_phase:
            self.checkpoints.load(latest, state)
            self.logs.rewind(counters.log)
        else:
            counters.phase_frames = [0] * n
        counters.in_phase = True
        frames_before = counters.frames - collector.frames // n
        loop = Trainer(
            collector,
            stops,
            phase,
            eval_every=int(cfg.eval_every),
            checkpoints=self.checkpoints,
            state=state,
            seeds=n,
            frames_before=frames_before,
            where=self._where(start_stage),
            watch=watch,
            progress=self.progress,
            open_ended=can_stop_early(cfg),
            seed_names=self.seeds,
        )

        def on_batch(batch: TensorDictBase) -> None:
            counters.frames = frames_before + collector.frames // n
            with watch("collect"):
                self._route(batch, stops.active(), counters)

        loop.register_op("batch", on_batch)
        loop.register_op("update", lambda frames: self._update(stops.active(), counters, watch))
        loop.register_op(
            "log", lambda batch, losses: self._log_batch(k, batch, losses, counters, stops)
        )
        loop.register_op("evaluate", lambda frames: self.evaluate(k, eval_env, counters, stops))
        loop.register_op("evaluated", functools.partial(self._evaluated, k, counters, stops))
        loop.register_op("checkpoint", lambda: self._record(counters, t0))
        loop.train()
        for i in range(n):
            restored = stops.finish(i)
            at, early = stops.stopped_at[i], stops.monitors[i]
            if at is not None and "moments" in at:  # the Adam moments it stopped with
                seed_moments(self.learners, i, load=at["moments"])
            success, value_error = early.final
            counters.phases[i].append(
                {
                    "start_stage": start_stage,
                    "frames": counters.phase_frames[i],
                    "success_rate": success,
                    "value_error": value_error,
                    "discounted_return": early.final_return,
                    "early_stopped": early.stopped,
                    "restored_best": restored,
                }
            )

    def _where(self, start_stage: int | None) -> str:
        """The phase from ``start_stage`` in messages, on its progress bar and in its log
        lines."""
        if start_stage is None:
            return "the joint phase from the task's own starts"
        return f"the joint phase from stage {start_stage} ({self.task.stage_names[start_stage]})"

    def _record(self, counters: JointCounters, start: float) -> None:
        counters.seconds = time.perf_counter() - start
        counters.log = self.logs.position()

    def _evaluated(
        self, k: int, counters: JointCounters, stops: SeedEarlyStops, evaluation: Evaluation
    ) -> None:
        """After an evaluation: a seed that stopped while others train on keeps its Adam
        moments (the others' updates decay them); the probe follows the whole task."""
        if self.n > 1:
            for i, at in enumerate(stops.stopped_at):
                if at is not None and "moments" not in at:
                    at["moments"] = seed_moments(self.learners, i)
        if self.probe is not None and k == 0:
            self.probe(self.learners, counters.frames)

    def _route(self, batch: TensorDictBase, active: list[int], counters: JointCounters) -> None:
        """Each transition of a seed still training into its seed's ring of the buffer of
        the stage of its state s_t (a stopped seed's are dropped), counted in its stage's
        ``stored``, its phase's frames and its run's ``trained`` frames."""
        n = self.n
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
                    counters.stored[i][m] += count
        for i in active:
            counters.phase_frames[i] += parts.shape[1]
            counters.trained[i] += parts.shape[1]

    def _update(
        self, active: list[int], counters: JointCounters, watch: Stopwatch
    ) -> dict[int, list[dict]]:
        """Every stage takes its gradient steps, the last stage first, for the seeds still
        training that hold enough of its transitions (the others' rows are left out); the
        transitions that leave the stage get their reward at sampling time."""
        n, stored = self.n, counters.stored
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
                    with watch("sample"):
                        drawn = self.buffers[m].sample(size * per_draw, rows)
                        if learner.seeds is None:  # an ordinary learner reads [batch] samples
                            drawn = drawn[0]
                    for sample in drawn.split(size, dim=-1):
                        with watch("sample"), update_rows(rows):  # stage m's view, now
                            sample = self.transforms[m](sample)
                        with watch("update"), update_rows(rows):
                            keep_threads()
                            losses[m].append(per_seed_metrics(learner.update(sample), rows, n))
                learner.check_finite()
            except (NonFiniteError, NonFiniteValueError) as err:
                raise stage_failure(
                    err,
                    m,
                    self.task.stage_names[m],
                    learner,
                    self.buffers[m].held(),
                    [team_rows(self.learners)[i] for i in ready],
                    [self.seeds[i] for i in ready],
                ) from err
            for i in ready:
                counters.updates[i][m] += steps
        return losses

    @torch.no_grad()
    def evaluate(
        self, k: int, eval_env, counters: JointCounters, stops: SeedEarlyStops
    ) -> Evaluation:
        """Greedy whole-task episodes from stage-k starts, for each seed: success, merged value
        error and merged discounted return (the seeds still training log theirs under
        ``eval/joint_<k>/``)."""
        cfg = self.task.stage_cfg(k)
        policy = StackedPolicy([learner.policy for learner in self.learners])
        max_steps = int(getattr(eval_env.base_env, "max_steps", 1000))
        if cfg.eval_max_steps:  # each stage an episode crosses may take eval_max_steps
            max_steps = min(max_steps, int(cfg.eval_max_steps) * (self.task.num_stages - k))
        summaries = evaluate_greedy(
            eval_env,
            policy,
            self._value,
            max_steps,
            self.gammas,
            cfg.value_error_reduce,
            groups=self.n,
        )
        for i in stops.active():
            metrics = {metric_name("eval", JOINT, k, key): v for key, v in summaries[i].items()}
            self.logs[i](metrics, counters.trained[i])
        return Evaluation(
            [s["success_rate"] for s in summaries],
            [s["value_error"] for s in summaries],
            [s["discounted_return"] for s in summaries],
            list(counters.phase_frames),
            [sum(u) for u in counters.updates],
        )

    # ------------------------------------------------------------------ state and logs
    def _learner_states(self) -> list[dict]:
        return [learner.checkpoint() for learner in self.learners]

    def _load_learner_states(self, states: Sequence[dict]) -> None:
        for learner, state in zip(self.learners, states, strict=True):
            learner.load_checkpoint(state)

    def _log_batch(
        self,
        k: int,
        batch: TensorDictBase,
        losses: dict[int, list[dict]],
        counters: JointCounters,
        stops: SeedEarlyStops,
    ) -> None:
        if self.logs.silent:
            return
        episodes = MetricsLog.episodes_by_row(batch.reshape(self.n, -1))
        means = {m: loss_means(stage_losses) for m, stage_losses in losses.items()}
        for i in stops.active():
            metrics = {metric_name("train", JOINT, k, key): v for key, v in episodes[i].items()}
            for m, stage_means in means.items():
                values = {key: v[i] for key, v in stage_means.items()}
                if all(v != v for v in values.values()):  # NaN: seed i's stage m waits for data
                    continue
                for key, value in {**values, "updates": counters.updates[i][m]}.items():
                    metrics[metric_name("train", STAGE, m, key)] = value
            self.logs[i](metrics, counters.trained[i])


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


def train_joint(
    task: StagedTask,
    seeds: Sequence[int] = (0,),
    *,
    keepers: Sequence[StageKeeper | None] | None = None,
    logs: Sequence[MetricsLog] | None = None,
    checkpoints: Any = None,
    progress: bool = False,
    probe: Probe | None = None,
    compile: str = "off",
) -> list[Trained]:
    """The joint schedule for every seed of ``seeds`` at once (:class:`JointTrainer`);
    ``keepers``, ``logs`` and ``checkpoints`` (called with ``"joint"``) as in
    :func:`~torchrl_stages.schedules.backward.train_backward`. A run every seed's keeper has
    finished is loaded, not trained."""
    n, stages = len(seeds), task.num_stages
    keepers = list(keepers) if keepers is not None else [None] * n
    resume = "stages-train schedule=joint seed=<s> resume=true hydra.run.dir=<its directory>"
    done = [finished_for_every_seed(keepers, seeds, k, resume) for k in range(stages)]
    if all(d is not None for d in done):
        return [
            Trained(
                [done[k][i][0] for k in range(stages)],
                [done[k][i][1] for k in range(stages)],
                {"phases": list(keepers[i].kept("phases") or [])},
            )
            for i in range(n)
        ]
    scope = begin_loop(keepers, checkpoints, "joint")
    trainer = JointTrainer(
        task, seeds, logs=logs, progress=progress, checkpoints=scope, probe=probe, compile=compile
    )
    runs = trainer.train()
    for seed, keeper, run in zip(seeds, keepers, runs, strict=True):
        log_phases(run.extra["phases"], "joint" if n == 1 else f"seed {seed}: joint")
        if keeper is not None:
            keep_joint(keeper, run.learners, run.results, run.extra["phases"])
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

    def train(self, task: StagedTask, seeds: Sequence[int] = (0,), **kwargs) -> list[Trained]:
        return train_joint(task, seeds, **kwargs)


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
    keeper: StageKeeper,
    learners: Sequence[Learner],
    results: Sequence[StageResult],
    phases: Sequence[dict[str, Any]],
) -> None:
    """Keeps a finished joint run in ``keeper``: its phases (for a resumed launch's
    ``eval.json``) and every stage; its checkpoints go."""
    keeper.keep("phases", list(phases))
    for k, (learner, result) in enumerate(zip(learners, results, strict=True)):
        keeper.save(k, learner, result)
    keeper.clear("joint")
