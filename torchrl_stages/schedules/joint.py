"""The paper's Algorithm 1 (``schedule=joint``): every stage learner keeps learning while the
start region moves back, phase k collecting whole-task episodes from stage-k starts."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, RewardSum, TransformedEnv

from torchrl_stages.checkpoint import StateOf
from torchrl_stages.early_stop import Evaluation, SeedEarlyStops
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.learners.stacking import unstack_learner
from torchrl_stages.loop import Stopwatch
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.schedules.base import Probe, Schedule, SeedGroup, Trained, register_schedule
from torchrl_stages.schedules.team import JointCounters, StageTeam
from torchrl_stages.seeding import EVAL_OFFSET, phase_seed, stage_seed
from torchrl_stages.stage import StageResult
from torchrl_stages.task import StagedTask, tile_starts
from torchrl_stages.transforms import StageTransform

log = logging.getLogger(__name__)

#: the metrics scope of the phases (``eval/joint_<k>/...``: the phase from stage k)
JOINT = "joint"


class JointTrainer(StageTeam):
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
        self, task: StagedTask, seeds: Sequence[int] = (0,), *, probe: Probe | None = None, **kwargs
    ) -> None:
        super().__init__(task, seeds, **kwargs)
        self.probe = probe
        self.starts = list(reversed(range(task.num_stages))) if task.stage_starts else [None]

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
        latest = self.latest(counters, "joint")
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
            learner.num_updates = counters.updates[i][m]
            learners.append(learner)
            frames = counters.stored[i][m]
            timing = dict(watch.seconds)
            results.append(
                StageResult(m, frames, learner.num_updates, seconds, timing=timing, **ended)
            )
        return Trained(learners, results, {"phases": phases})

    def _phase(self, start_stage, counters: JointCounters, stateful, latest, watch, t0) -> None:
        """One phase for every seed, from ``start_stage``'s starts."""
        n, k = self.n, 0 if start_stage is None else start_stage
        cfg = self.task.stage_cfg(k)
        resume_in_phase = latest is not None and counters.in_phase
        if latest is not None and not resume_in_phase:  # resumed at a phase boundary
            self.restore(latest, stateful, counters)
        env, eval_env = self._phase_envs(k, start_stage, cfg)
        policy = StackedPolicy(
            [learner.exploration_policy for learner in self.learners], skip_absent=False
        )
        where = "the joint phase from " + (
            "the task's own starts"
            if start_stage is None
            else f"stage {start_stage} ({self.task.stage_names[start_stage]})"
        )
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
            latest=latest if resume_in_phase else None,
            start=t0,
            init_random=counters.phase == 0,
        )
        collector, stops = loop.collector, loop.early_stop
        if not resume_in_phase:
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
        for i in range(n):
            ended = stops.finish(i)
            frames = counters.phase_frames[i]
            counters.phases[i].append({"start_stage": start_stage, "frames": frames, **ended})

    def evaluate(
        self, k: int, eval_env, counters: JointCounters, stops: SeedEarlyStops
    ) -> Evaluation:
        """Greedy whole-task episodes from stage-k starts for each seed."""
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
            return [
                Trained(
                    [done[k][i][0] for k in stages],
                    [done[k][i][1] for k in stages],
                    {"phases": list(keepers[i].kept("phases") or [])},
                )
                for i in range(len(seeds))
            ]
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
            phases = run.extra["phases"]
            log_phases(phases, "joint" if len(seeds) == 1 else f"seed {seed}: joint")
            if keeper is not None:  # its phases, for a resumed launch's eval.json
                keeper.keep("phases", list(phases))
                for k, learner in enumerate(run.learners):
                    keeper.save(k, learner, run.results[k])
                keeper.clear("joint")
        if scope is not None:
            scope.clear()
        return trained


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
