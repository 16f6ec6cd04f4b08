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
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import Compose, RewardSum, TransformedEnv
from torchrl.record.loggers import Logger

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.collector import StageCollector
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.loop import (
    EarlyStop,
    MetricsLog,
    Stopwatch,
    first_evaluation,
    run_loop,
)
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.replay import stage_replay_buffer
from torchrl_stages.schedules.base import Schedule, StageStore, Trained, register_schedule
from torchrl_stages.stage import StageResult, stage_failure
from torchrl_stages.task import StagedTask
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
        >>> from torchrl_stages.task import StagedTask
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
        self.keys = [self._stored_keys(m) for m in range(n)]
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

    def _stored_keys(self, m: int) -> list[NestedKey]:
        """What stage m's buffer keeps: its loss's entries, the stage tags, and what the next
        stage's value reads from s_{t+1}."""
        keys = [*self.learners[m].replay_keys, *TAGS]
        transform = self.buffers[m].transform[0]
        if transform.next_value is not None:
            keys += [
                ("next", k) if isinstance(k, str) else ("next", *k)
                for k in transform.next_value.in_keys
            ]
        return list(dict.fromkeys(keys))

    def _env(self, start: int | None, batch_size: int, eval_env: bool = False):
        """Whole-task env from stage ``start``'s starts (tags only, no learner view)."""
        task = self.task
        starts = task.start_states(start) if eval_env else None
        if starts is not None:
            base = task.base_env(**starts)
        else:
            base = task.base_env(batch_size, start_stage=start)
        tags = StageTransform(base.stage_fn, base.num_stages)
        return TransformedEnv(base, tags if eval_env else Compose(tags, RewardSum()))

    # ------------------------------------------------------------------ training
    def train(self) -> tuple[list[Learner], list[StageResult], list[dict[str, Any]]]:
        """Runs every phase; returns the learners, one result per stage and one per phase."""
        counters: dict[str, Any] = {
            "phase": 0,
            "frames": 0,  # every phase's frames so far
            "stored": [0] * self.task.num_stages,
            "seconds": 0.0,
            "phases": [],
            "log": {},
            "in_phase": False,
        }
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
        seconds = time.perf_counter() - start
        last = counters["phases"][-1] if counters["phases"] else {}
        results = [
            StageResult(
                m,
                counters["stored"][m],
                learner.num_updates,
                seconds,
                last.get("success_rate"),
                last.get("value_error"),
                bool(last.get("early_stopped", False)),
                bool(last.get("restored_best", False)),
                dict(watch.seconds),
                last.get("discounted_return"),
            )
            for m, learner in enumerate(self.learners)
        ]
        return self.learners, results, counters["phases"]

    def _phase(self, start_stage, counters, stateful, latest, watch, t0) -> None:
        """One phase: collect from ``start_stage``'s starts, route, update every stage, evaluate."""
        task = self.task
        k = 0 if start_stage is None else start_stage
        cfg = task.stage_cfg(k)
        resume_in_phase = latest is not None and counters["in_phase"]
        if latest is not None and not resume_in_phase:  # resumed at a phase boundary
            self.checkpoints.load(latest, stateful)
            self.log.rewind(counters["log"])
        torch.manual_seed(self.seed + 1000 * (k + 1))
        env = self._env(start_stage, int(cfg.num_envs))
        env.set_seed(self.seed + k)
        eval_env = self._env(start_stage, int(cfg.eval_episodes), eval_env=True)
        eval_env.set_seed(self.seed + 10_000 + k)
        collector = StageCollector(
            env,
            StackedPolicy([learner.exploration_policy for learner in self.learners]),
            frames_per_batch=int(cfg.frames_per_batch),
            total_frames=int(cfg.frames),
            init_random_frames=int(cfg.init_random_frames) if counters["phase"] == 0 else 0,
        )
        monitor = EarlyStop(cfg)
        phase = {"next_eval": first_evaluation(cfg)}
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
            where=f"the joint phase from stage {k}",
            watch=watch,
            progress=self.progress,
            count=count,
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


@register_schedule
class JointSchedule(Schedule):
    """``schedule=joint`` (:class:`JointTrainer`): every stage trains at once, so the run
    resumes as a whole (checkpoints ``"joint"``) and its stage files are written when it ends;
    its phases, not its stages, stop early."""

    name = "joint"
    stage_early_stop = False

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
        for phase in phases:
            start = phase["start_stage"]
            log.info(
                "joint phase from %s: %d frames, whole-task success %.2f, value error %.3f%s",
                "the task's own starts" if start is None else f"stage {start} starts",
                phase["frames"],
                phase["success_rate"] if phase["success_rate"] is not None else float("nan"),
                phase["value_error"] if phase["value_error"] is not None else float("nan"),
                " (early stop)" if phase["early_stopped"] else " (budget used, best restored)",
            )
        if store is not None:
            store.keep("phases", phases)  # for a resumed launch's eval.json
            for k in range(n):
                store.save(k, learners[k], results[k])
            store.clear("joint")
        return Trained(learners, results, {"phases": phases})
