"""The paper's Algorithm 1 (``schedule=joint``): every stage learner keeps learning while the
start region moves back, phase k collecting whole-task episodes from stage-k starts; one replay
buffer per stage, each transition rewarded, as it leaves its stage, with the next one's value."""

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
from tensordict.utils import NestedKey, unravel_key
from torchrl.envs import Compose, RewardSum, TransformedEnv

from torchrl_stages.checkpoint import CHECKPOINT_FORMAT, SavedCounters, StageCheckpoints, StateOf
from torchrl_stages.early_stop import Evaluation, SeedEarlyStops, seed_rows
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.failures import stage_failures
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.stacking import stack_learners, unstack_learner
from torchrl_stages.loop import SeedLoop, Stopwatch
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.schedules.base import Probe, Schedule, SeedGroup, Trained, register_schedule
from torchrl_stages.seeding import EVAL_OFFSET, phase_seed, stage_seed
from torchrl_stages.stage import StageResult, gradient_steps
from torchrl_stages.task import StagedTask, tile_starts
from torchrl_stages.transforms import StageRewardTransform, StageTransform

log = logging.getLogger(__name__)

#: the metrics scope of the phases (``eval/joint_<k>/...``: the phase from stage k)
JOINT = "joint"


_NEXT_TAGS = ("stage", "stage_transition", "reward", "terminated", "truncated", "done")
#: what every stage's buffer keeps besides its loss's entries
TAGS: tuple[NestedKey, ...] = ("stage", *(("next", key) for key in _NEXT_TAGS))


@dataclass
class JointCounters(SavedCounters):
    """What a joint run counts (per seed where seeds differ), saved with its checkpoints."""

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


class JointTrainer(SeedLoop):
    """Trains all stage learners of ``task`` together for every seed of ``seeds`` at once.

    Phase k (k = N-1, ..., 0; without stage starts: one phase from the task's own) collects
    whole-task episodes from stage-k starts with stage k's keys; the transitions leaving stage m
    are rewarded ``r + gamma_m V_{m+1}(s')`` from stage m+1's live target networks. The seeds
    share the envs' random streams, the exploration schedules and the Adam step counts.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> tiny = DQNConfig(frames=512, frames_per_batch=128, num_envs=16,
        ...                  init_random_frames=128, batch_size=32, eval_every=0)
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10, "num_stages": 2}
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": {"a": tiny, "b": tiny},
        ...                                     "env": env}))
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
        compile: str = "off",
        probe: Probe | None = None,
    ) -> None:
        super().__init__(len(seeds), logs, seeds, progress, checkpoints)
        self.task, stages = task, task.num_stages
        self.make = [
            functools.partial(make_learner, task.stage_cfg(m), task.specs(m), compile, task.device)
            for m in range(stages)
        ]
        self.learners = self._seeded_learners()
        self.rows = seed_rows(self.learners, moments=True)  # what an early stop keeps of a seed
        self.gammas = [float(task.stage_cfg(m).gamma) for m in range(stages)]
        self.transforms, self.buffers, self.keys = [], [], []
        for m, learner in enumerate(self.learners):
            next_value = self.learners[m + 1].value(live=True) if m + 1 < stages else None
            self.transforms.append(
                StageRewardTransform(m, stages, next_value=next_value, gamma=self.gammas[m])
            )
            size = int(task.stage_cfg(m).buffer_size)
            self.buffers.append(SeedReplayBuffer(size, num_seeds=self.n, device=learner.device))
            # stage m's loss entries, the tags, what the next stage's value reads
            keys = [*learner.replay_keys, *TAGS]
            if next_value is not None:
                keys += [unravel_key(("next", k)) for k in next_value.in_keys]
            self.keys.append(list(dict.fromkeys(keys)))
        self.probe = probe
        self.starts = list(reversed(range(stages))) if task.stage_starts else [None]

    def _seeded_learners(self) -> list[Learner]:
        """Every stage's learner; row i of a stacked one: what ``seeds[i]`` alone starts from."""
        stages = range(self.task.num_stages)
        rows: list[list[Learner]] = [[] for _ in stages]
        for seed in self.seeds:  # each seed's generator builds its stages 0..N-1 in turn
            torch.manual_seed(seed)
            for m in stages:
                rows[m].append(self.make[m]())
        if self.n == 1:
            return [row[0] for row in rows]
        return [stack_learners(self.make[m](seeds=self.n), rows[m]) for m in stages]

    @functools.cached_property
    def _value(self) -> StackedPolicy:
        """What evaluations read V from: every stage's target networks themselves (live)."""
        return StackedPolicy([learner.value(live=True) for learner in self.learners])

    def _route(self, batch: TensorDictBase, active: list[int], counters: JointCounters) -> None:
        """Stores each training seed's transitions in the buffer of the stage of s_t, counted."""
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
        """Every stage's gradient steps, last stage first, for the training seeds ready for it."""
        stored, losses = counters.stored, {}
        for m in reversed(range(self.task.num_stages)):
            cfg, learner = self.task.stage_cfg(m), self.learners[m]
            need = max(int(cfg.init_random_frames), int(cfg.batch_size), 1)
            ready = [i for i in active if stored[i][m] >= need]
            if not ready:
                continue
            learner.anneal(round(statistics.mean(stored[i][m] for i in ready)))
            buffer, name = self.buffers[m], self.task.stage_names[m]
            kept, seeds = [self.rows[i] for i in ready], [self.seeds[i] for i in ready]
            with stage_failures(m, name, learner, buffer, kept, seeds):
                losses[m] = gradient_steps(learner, buffer, cfg, ready, watch, self.transforms[m])
            for i in ready:
                counters.updates[i][m] += int(cfg.updates_per_batch)
        return losses

    def _learner_states(self) -> list[dict]:
        return [learner.checkpoint() for learner in self.learners]

    def _load_learner_states(self, states: Sequence[dict]) -> None:
        for learner, state in zip(self.learners, states, strict=True):
            learner.load_checkpoint(state)

    def _phase_envs(self, k: int, start_stage: int | None, cfg) -> tuple[Any, Any]:
        """Phase ``k``'s whole-task training and evaluation envs from stage ``start_stage``'s
        starts, their batch repeated once per seed, seeded (the global generator too)."""
        task, seed, n = self.task, self.seeds[0], self.n
        torch.manual_seed(phase_seed(seed, k))
        base = task.base_env(int(cfg.num_envs) * n, start_stage=start_stage)
        tags = StageTransform(base.stage_fn, base.num_stages)
        env = TransformedEnv(base, Compose(tags, RewardSum()))
        env.set_seed(stage_seed(seed, k))
        starts = task.start_states(start_stage)
        if starts is not None:
            base = task.base_env(**tile_starts(starts, n))
        else:
            base = task.base_env(int(cfg.eval_episodes) * n, start_stage=start_stage)
        eval_env = TransformedEnv(base, StageTransform(base.stage_fn, base.num_stages))
        eval_env.set_seed(stage_seed(seed, k) + EVAL_OFFSET)
        return env, eval_env

    def train(self) -> list[Trained]:
        """Runs every phase from the newest checkpoint on; one :class:`Trained` per seed."""
        counters = JointCounters(self.task.num_stages, self.n)
        stateful = {
            "learners": StateOf(self._learner_states, self._load_learner_states),
            "counters": counters,
            **{f"replay_buffer_{m}": b for m, b in enumerate(self.buffers)},
        }
        latest = self.latest(counters, "joint", stateful)
        if latest is not None and not counters.in_phase:  # resumed at a phase boundary
            self.restore(latest, stateful, counters)
            latest = None
        start = time.perf_counter() - counters.seconds
        watch = Stopwatch()
        for index in range(counters.phase, len(self.starts)):
            counters.phase = index
            self._phase(self.starts[index], counters, stateful, latest, watch, start)
            latest = None
            counters.phase, counters.in_phase = index + 1, False
            if self.checkpoints is not None:  # a phase boundary: learners and buffers
                self.record(counters, start)
                self.checkpoints.save(counters.frames, stateful)
        seconds = time.perf_counter() - start  # every launch's
        return [self._trained(i, counters, seconds, watch) for i in range(self.n)]

    def _trained(self, i: int, counters: JointCounters, seconds: float, watch) -> Trained:
        """Seed ``i``'s learners and results (the last phase's evaluation for every stage)."""
        phases = counters.phases[i]
        last = phases[-1] if phases else {}
        ended = {key: last.get(key) for key in ("success_rate", "value_error", "discounted_return")}
        ended |= {key: bool(last.get(key)) for key in ("early_stopped", "restored_best")}
        learners, results = [], []
        for m, learner in enumerate(self.learners):
            if learner.seeds is not None:
                learner = unstack_learner(learner, i, self.make[m]())
            learner.num_updates = updates = counters.updates[i][m]
            learners.append(learner)
            frames, timing = counters.stored[i][m], dict(watch.seconds)
            results.append(StageResult(m, frames, updates, seconds, timing=timing, **ended))
        return Trained(learners, results, {"phases": phases})

    def _phase(self, start_stage, counters: JointCounters, stateful, latest, watch, t0) -> None:
        """One phase for every seed, from ``start_stage``'s starts (``latest``: resumed in it)."""
        n, k = self.n, 0 if start_stage is None else start_stage
        cfg = self.task.stage_cfg(k)
        env, eval_env = self._phase_envs(k, start_stage, cfg)
        explore = [learner.exploration_policy for learner in self.learners]
        policy = StackedPolicy(explore, skip_absent=False)
        if start_stage is None:
            where = "the joint phase from the task's own starts"
        else:
            where = f"the joint phase from stage {k} ({self.task.stage_names[k]})"
        loop = self.loop(
            cfg,
            env,
            policy,
            eval_env,
            self.rows,
            stateful,
            where,
            watch,
            saved=counters,
            latest=latest,
            start=t0,
            init_random=counters.phase == 0,
        )
        collector, stops = loop.collector, loop.early_stop
        if latest is None:
            counters.phase_frames = [0] * n
        counters.in_phase = True
        frames_before = loop.frames_before = counters.frames - collector.frames // n

        def on_batch(batch: TensorDictBase) -> None:
            counters.frames = frames_before + collector.frames // n
            with watch("collect"):
                self._route(batch, stops.active(), counters)

        def on_log(batch: TensorDictBase, losses: dict[int, list[dict]]) -> None:
            active, updates, steps = stops.active(), counters.updates, counters.trained
            self.log_batch(batch, JOINT, k, losses, updates, active, steps)

        loop.register_op("batch", on_batch)
        loop.register_op("update", lambda frames: self._update(stops.active(), counters, watch))
        loop.register_op("log", on_log)
        loop.register_op("evaluate", lambda frames: self.evaluate(k, eval_env, counters, stops))
        if self.probe is not None and k == 0:
            loop.register_op("evaluated", lambda ev: self.probe(self.learners, counters.frames))
        loop.train()
        for i, phases in enumerate(counters.phases):
            frames = counters.phase_frames[i]
            phases.append({"start_stage": start_stage, "frames": frames, **stops.finish(i)})

    def evaluate(
        self, k: int, eval_env, counters: JointCounters, stops: SeedEarlyStops
    ) -> Evaluation:
        """Greedy whole-task episodes from stage-k starts for each seed."""
        cfg, n = self.task.stage_cfg(k), self.n
        policy = StackedPolicy([learner.policy for learner in self.learners])
        max_steps = int(getattr(eval_env.base_env, "max_steps", 1000))
        if cfg.eval_max_steps:  # each stage an episode crosses may take eval_max_steps
            max_steps = min(max_steps, int(cfg.eval_max_steps) * (self.task.num_stages - k))
        summaries = evaluate_greedy(
            eval_env, policy, self._value, max_steps, self.gammas, cfg.value_error_reduce, groups=n
        )
        active, steps = stops.active(), counters.trained
        frames, updates = list(counters.phase_frames), [sum(u) for u in counters.updates]
        return self.log_evaluation(summaries, JOINT, k, active, steps, frames, updates)


@register_schedule
class JointSchedule(Schedule):
    """``schedule=joint`` (:class:`JointTrainer`): the run resumes as a whole (checkpoints
    ``"joint"``), its stage files are written when it ends; its phases stop early."""

    name = "joint"
    stage_early_stop = False
    stacks_seeds = True

    def checkpoint_scope(self, stage: int) -> str:
        return "joint"

    def run(self, task: StagedTask, group: SeedGroup) -> list[Trained]:
        seeds, keepers, stages = group.seeds, group.keepers, range(task.num_stages)
        done = [group.finished(k) for k in stages]
        if all(d is not None for d in done):
            trained = Trained.per_seed(done)
            for run, keeper in zip(trained, keepers, strict=True):
                run.extra["phases"] = list(keeper.kept("phases") or [])
            return trained
        scope = group.begin("joint")
        trained = JointTrainer(
            task,
            seeds,
            logs=group.logs,
            progress=group.progress,
            checkpoints=scope,
            probe=group.probe,
            compile=group.compile,
        ).train()
        for seed, keeper, run in zip(seeds, keepers, trained, strict=True):
            who = "joint" if len(seeds) == 1 else f"seed {seed}: joint"
            for phase in run.extra["phases"]:  # one line per phase
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
            if keeper is not None:  # its phases, for a resumed launch's eval.json
                keeper.keep("phases", list(run.extra["phases"]))
                for k, learner in enumerate(run.learners):
                    keeper.save(k, learner, run.results[k])
                keeper.clear("joint")
        if scope is not None:
            scope.clear()
        return trained
