"""One stage's training for any number of seeds (:class:`StageTrainer`: several as one seed-stacked
learner sharing the env's random streams) and what it returns (:class:`StageResult`)."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_stages.checkpoint import StageCheckpoints, StateOf
from torchrl_stages.config import StageConfig
from torchrl_stages.early_stop import Evaluation, seed_rows
from torchrl_stages.evaluate import evaluate_greedy
from torchrl_stages.failures import stage_failures
from torchrl_stages.learners import Learner
from torchrl_stages.learners.stacking import unstack_learner, update_rows
from torchrl_stages.loop import LoopCounters, SeedLoop, Stopwatch, Trainer
from torchrl_stages.metric_names import STAGE
from torchrl_stages.metrics import MetricsLog
from torchrl_stages.replay import SeedReplayBuffer
from torchrl_stages.threads import keep_threads

__all__ = ["SeedResults", "StageResult", "StageTrainer", "gradient_steps", "per_seed_metrics"]


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
    timing: dict[str, float] = field(default_factory=dict)  # wall-clock seconds per loop phase
    # the stage's objective: mean greedy discounted return at that evaluation (joint schedule:
    # that of the whole-task episodes of its last phase, for every stage)
    discounted_return: float | None = None


#: each seed's learner and result of one stage
SeedResults = list[tuple[Learner, StageResult]]


def per_seed_metrics(
    metrics: dict[str, torch.Tensor], rows: torch.Tensor | None, n: int
) -> dict[str, torch.Tensor]:
    """An update's metrics per seed (``[n]``): those of ``rows`` alone in their rows, NaN elsewhere.

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


def gradient_steps(
    learner: Learner,
    buffer: SeedReplayBuffer,
    cfg: StageConfig,
    active: Sequence[int],
    watch: Stopwatch,
    transform: Callable[[TensorDictBase], TensorDictBase] | None = None,
) -> list[dict[str, torch.Tensor]]:
    """A batch's gradient steps of ``learner``'s ``active`` rows (the seeds still training, by
    position): one draw for all the steps unless the update itself draws random numbers (TD3)."""
    n = int(learner.seeds or 1)
    rows = None if len(active) == n else torch.tensor(active, device=learner.device)
    steps, size = int(cfg.updates_per_batch), int(cfg.batch_size)
    draws, per_draw = (steps, 1) if learner.update_draws_random else (min(steps, 1), steps)
    losses: list[dict[str, torch.Tensor]] = []
    for _ in range(draws):
        with watch("sample"):
            drawn = buffer.sample(size * per_draw, rows)
            if learner.seeds is None:  # an ordinary learner reads [batch] samples
                drawn = drawn[0]
        for sample in drawn.split(size, dim=-1):
            if transform is not None:
                with watch("sample"), update_rows(rows):
                    sample = transform(sample)
            with watch("update"), update_rows(rows):
                keep_threads()
                losses.append(per_seed_metrics(learner.update(sample), rows, n))
    learner.check_finite()
    return losses


class StageTrainer(SeedLoop):
    """Trains stage ``stage`` for every seed of ``learner`` (ordinary: one seed); ``env`` and
    ``eval_env`` hold one copy of their batch per seed, ``cfg``'s budgets are per seed. The flat
    schedule passes ``gammas`` (evaluations' stage discounts), ``postproc`` (applied to each
    batch) and ``extra_keys`` (stored too); ``on_evaluate(learner, frames)`` follows each
    evaluation. :meth:`train` returns each seed's ordinary learner (``make_learner()`` builds the
    one a stacked row is taken into) and result.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
        >>> from torchrl_stages.task import StagedTask
        >>> env = {"_target_": "torchrl_stages.envs.GridWorldEnv", "size": 10, "num_stages": 2}
        >>> stages = {"a": {"gamma": 0.9}, "b": {"gamma": 0.9}}
        >>> task = StagedTask(OmegaConf.create({"name": "grid", "stages": stages, "env": env}))
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
        on_evaluate: Callable[[Learner, int], None] | None = None,
    ) -> None:
        super().__init__(int(learner.seeds or 1), logs, seeds, progress, checkpoints)
        self.stage, self.learner, self.env, self.eval_env = stage, learner, env, eval_env
        self.cfg, self.make_learner, self.name = cfg, make_learner, name or str(stage)
        self.gammas, self.postproc, self.on_evaluate = gammas, postproc, on_evaluate
        self.keys = list(dict.fromkeys([*learner.replay_keys, *extra_keys]))

    @functools.cached_property
    def _value(self) -> TensorDictModuleBase:
        return self.learner.value(live=True)

    def train(self) -> SeedResults:
        learner, n = self.learner, self.n
        buffer = SeedReplayBuffer(int(self.cfg.buffer_size), num_seeds=n, device=learner.device)
        state = {
            "learner": StateOf(learner.checkpoint, learner.load_checkpoint),
            "replay_buffer": buffer,
        }
        where = f"stage {self.stage} ({self.name})"
        latest = self.latest(LoopCounters(0), where, state)
        watch = Stopwatch()
        policy, rows = learner.exploration_policy, seed_rows(learner)
        loop = self.loop(
            self.cfg, self.env, policy, self.eval_env, rows, state, where, watch, latest=latest
        )
        collector, stops = loop.collector, loop.early_stop

        def store(batch: TensorDictBase) -> None:
            with watch("collect"):
                if self.postproc is not None:
                    batch = self.postproc(batch)
                buffer.extend(batch.select(*self.keys, strict=False))

        def update(frames: int) -> list[dict[str, torch.Tensor]]:
            learner.anneal(frames)
            if frames < self.cfg.init_random_frames:
                return []
            return gradient_steps(learner, buffer, self.cfg, stops.active(), watch)

        def log(batch: TensorDictBase, losses: list[dict[str, torch.Tensor]]) -> None:
            updates, steps = [{self.stage: learner.num_updates}] * n, [collector.frames // n] * n
            stage_losses = {self.stage: losses}
            self.log_batch(batch, STAGE, self.stage, stage_losses, updates, stops.active(), steps)

        loop.register_op("batch", store)
        loop.register_op("update", update)
        loop.register_op("log", log)
        loop.register_op("evaluate", functools.partial(self.evaluate, active=stops.active))
        if self.on_evaluate is not None:
            loop.register_op("evaluated", lambda ev: self.on_evaluate(learner, ev.frames[0]))
        with stage_failures(self.stage, self.name, learner, buffer, stops.rows, self.seeds):
            loop.train()
        return [self._result(i, loop) for i in range(n)]

    def evaluate(self, frames: int, active: Callable[[], list[int]] | None = None) -> Evaluation:
        """Greedy episodes from the evaluation env's starts for each seed (``active``: logged)."""
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
        seeds = active() if active is not None else range(n)
        steps, updates = [frames] * n, [self.learner.num_updates] * n
        return self.log_evaluation(summaries, STAGE, self.stage, seeds, steps, steps, updates)

    def _result(self, i: int, loop: Trainer) -> tuple[Learner, StageResult]:
        stops = loop.early_stop
        at, ended = stops.stopped_at[i], stops.finish(i)
        result = StageResult(
            self.stage,
            loop.collector.frames // self.n if at is None else at["frames"],
            self.learner.num_updates if at is None else at["updates"],
            time.perf_counter() - stops.start if at is None else at["seconds"],
            timing=dict(loop.watch.seconds),
            **ended,
        )
        if self.learner.seeds is None:
            return self.learner, result
        plain = unstack_learner(self.learner, i, self.make_learner())
        plain.num_updates, plain.stacked_row = result.updates, (self.learner, i)
        return plain, result
