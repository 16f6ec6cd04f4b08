"""Every stage learner of a task trained together for several seeds (:class:`StageTeam`): one
replay buffer per stage, each transition stored in that of its state's stage and rewarded, when
it leaves the stage, with the next stage's live value."""

from __future__ import annotations

import functools
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key

from torchrl_stages.checkpoint import CHECKPOINT_FORMAT, SavedCounters, StageCheckpoints
from torchrl_stages.early_stop import seed_rows
from torchrl_stages.failures import stage_failures
from torchrl_stages.learners import Learner, make_learner
from torchrl_stages.learners.stacking import stack_learners
from torchrl_stages.loop import SeedLoop, Stopwatch
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.policy import StackedPolicy
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.stage import gradient_steps
from torchrl_stages.task import StagedTask
from torchrl_stages.transforms import StageRewardTransform

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


class StageTeam(SeedLoop):
    """Every stage's learner of ``task`` for each seed of ``seeds`` (several: seed-stacked), with
    its replay buffer and transition reward."""

    def __init__(
        self,
        task: StagedTask,
        seeds: Sequence[int] = (0,),
        *,
        logs: Sequence[MetricsLog] | None = None,
        progress: bool = False,
        checkpoints: StageCheckpoints | None = None,
        compile: str = "off",
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
                int(task.stage_cfg(m).buffer_size), num_seeds=self.n, device=self.learners[m].device
            )
            for m in range(stages)
        ]
        self.keys = []  # stage m's loss entries, the tags, what the next stage's value reads
        for m, transform in enumerate(self.transforms):
            keys = [*self.learners[m].replay_keys, *TAGS]
            if transform.next_value is not None:
                keys += [unravel_key(("next", k)) for k in transform.next_value.in_keys]
            self.keys.append(list(dict.fromkeys(keys)))

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
            rows = None if len(ready) == self.n else torch.tensor(ready, device=learner.device)
            buffer, name = self.buffers[m], self.task.stage_names[m]
            kept, seeds = [self.rows[i] for i in ready], [self.seeds[i] for i in ready]
            with stage_failures(m, name, learner, buffer, kept, seeds):
                losses[m] = gradient_steps(learner, buffer, cfg, rows, watch, self.transforms[m])
            for i in ready:
                counters.updates[i][m] += int(cfg.updates_per_batch)
        return losses

    def _learner_states(self) -> list[dict]:
        return [learner.checkpoint() for learner in self.learners]

    def _load_learner_states(self, states: Sequence[dict]) -> None:
        for learner, state in zip(self.learners, states, strict=True):
            learner.load_checkpoint(state)
