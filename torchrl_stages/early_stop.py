"""When a loop stops, and which weights it keeps: each seed's greedy evaluations
(:class:`Evaluation`), the early stop and best weights of one seed (:class:`EarlyStop`) and of
every seed of a loop (:class:`SeedEarlyStops`), over the rows of a seed-stacked learner
(:class:`SeedRow`, :class:`TeamRow`; an ordinary learner is its own one row)."""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from torchrl_stages.config import StageConfig
from torchrl_stages.learners import Learner
from torchrl_stages.learners.stacking import seed_axes

__all__ = [
    "EarlyStop",
    "Evaluation",
    "SeedEarlyStops",
    "SeedRow",
    "TeamRow",
    "first_evaluation",
    "seed_rows",
]


def first_evaluation(cfg: StageConfig) -> int:
    """Frames of a stage's first evaluation: ``eval_every``, or, with an early stop that the
    budget allows, the first of the ``patience`` evaluations that can stop the stage at
    ``min_frames`` (earlier ones could not stop it: evaluations only as often as the early stop
    needs)."""
    first = int(cfg.eval_every)
    if cfg.success_threshold is not None and int(cfg.min_frames) <= int(cfg.frames):
        first = max(first, int(cfg.min_frames) - (int(cfg.patience) - 1) * first)
    return first


@dataclass
class Evaluation:
    """One evaluation of every seed of a loop (lists: one entry per seed): greedy success,
    value error and mean discounted return, and each seed's frames and updates so far."""

    success: list[float]
    value_error: list[float]
    discounted_return: list[float | None]
    frames: list[int]
    updates: list[int]


class EarlyStop:
    """Early stop and best-weights bookkeeping over a stage's greedy evaluations.

    The early-stop criterion must hold for ``patience`` consecutive evaluations after
    ``min_frames``. When the budget runs out first, :meth:`restore_best` puts back the weights of
    the best evaluation, if ``keep_best``: highest success, then lowest value error (``keep_best_by
    = "value_error"``) or highest mean discounted return (``"return"``).
    """

    def __init__(self, cfg: StageConfig) -> None:
        self.cfg = cfg
        self.streak = 0
        self.stopped = False
        self.best: tuple[float, float] | None = None  # (success, value error) of the best
        self.best_score: tuple[float, float] | None = None
        self.best_is_last = False
        self.best_state: dict | None = None
        self.last: tuple[float, float] | None = None
        self.best_return: float | None = None  # mean discounted return of those evaluations
        self.last_return: float | None = None

    def record(
        self,
        learner: nn.Module,
        success: float,
        value_error: float,
        frames: int,
        ret: float | None = None,
    ) -> bool:
        """Records one evaluation (``ret``: its mean discounted return); returns whether the
        stage should stop now."""
        cfg = self.cfg
        self.last, self.last_return = (success, value_error), ret
        by_return = 0.0 if ret is None else ret
        score = (success, by_return if cfg.keep_best_by == "return" else -value_error)
        self.best_is_last = cfg.keep_best and (self.best_score is None or score > self.best_score)
        if self.best_is_last:
            self.best_score, self.best = score, (success, value_error)
            self.best_return = ret
            self.best_state = copy.deepcopy(learner.state_dict())
        met = (
            cfg.success_threshold is not None
            and success >= cfg.success_threshold
            and (cfg.value_tolerance is None or value_error <= cfg.value_tolerance)
        )
        self.streak = self.streak + 1 if met else 0
        self.stopped = self.streak >= cfg.patience and frames >= cfg.min_frames
        return self.stopped

    _FIELDS = (
        "streak",
        "stopped",
        "best",
        "best_score",
        "best_is_last",
        "last",
        "best_return",
        "last_return",
    )

    def state_dict(self) -> dict:
        return {**{f: getattr(self, f) for f in self._FIELDS}, "best_state": self.best_state}

    def load_state_dict(self, state: dict) -> None:
        for f in self._FIELDS:
            # checkpoints from before the returns were kept lack those two fields
            value = state.get(f) if f.endswith("_return") else state[f]
            setattr(self, f, tuple(value) if isinstance(value, list) else value)
        self.best_state = state["best_state"]

    def restore_best(self, learner: nn.Module) -> bool:
        """Puts back the best evaluated weights (the budget ran out before the early stop);
        returns whether they differ from the weights the loop ended with (updates may follow
        the last evaluation)."""
        if self.stopped or self.best_state is None:
            return False
        current = learner.state_dict()
        changed = any(not torch.equal(current[k], v) for k, v in self.best_state.items())
        if changed:
            learner.load_state_dict(self.best_state)
        return changed

    @property
    def final(self) -> tuple[float | None, float | None]:
        """Evaluation of the weights the stage ends with."""
        if self.last is None:
            return None, None
        if self.stopped or self.best is None:
            return self.last
        return self.best  # restore_best puts these weights back

    @property
    def final_return(self) -> float | None:
        """Mean discounted return of the evaluation :attr:`final` reports."""
        if self.stopped or self.best is None:
            return self.last_return
        return self.best_return


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


def seed_rows(learner: Learner) -> list[Any]:
    """What an early stop keeps and restores of each seed of ``learner``: its rows
    (:class:`SeedRow`) when it is seed-stacked, the learner itself when it is not."""
    if learner.seeds is None:
        return [learner]
    return [SeedRow(learner, i) for i in range(int(learner.seeds))]


def finite(state: dict[str, torch.Tensor]) -> bool:
    """Whether every floating-point entry of ``state`` is finite."""
    return all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point())


class SeedEarlyStops:
    """One :class:`EarlyStop` per seed, over ``rows`` (one per seed: :func:`seed_rows`, or a
    :class:`TeamRow`): :meth:`record` takes an :class:`Evaluation` and says whether every seed
    has stopped; a seed that stops has its weights (its row), frames, updates and seconds
    kept (:attr:`stopped_at`) while the others train on.

    Examples:
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> cfg = DQNConfig(success_threshold=0.9, value_tolerance=None, patience=1)
        >>> stops = SeedEarlyStops(cfg, [nn.Linear(1, 1), nn.Linear(1, 1)])
        >>> stops.record(Evaluation([1.0, 0.5], [0.0, 0.0], [None, None], [64, 64], [8, 8]))
        False
        >>> stops.active(), stops.stopped_at[0]["frames"]
        ([1], 64)
    """

    def __init__(self, cfg: StageConfig, rows: Sequence[Any], start: float = 0.0) -> None:
        self.start = start  # what stop times are measured from
        self.rows = list(rows)
        self.monitors = [EarlyStop(cfg) for _ in self.rows]
        self.stopped_at: list[dict | None] = [None] * len(self.rows)

    def record(self, evaluation: Evaluation) -> bool:
        """Records each active seed's evaluation; returns whether every seed has stopped."""
        ev = evaluation
        for i, monitor in enumerate(self.monitors):
            if self.stopped_at[i] is not None:
                continue
            row = self.rows[i]
            args = (ev.success[i], ev.value_error[i], ev.frames[i], ev.discounted_return[i])
            if monitor.record(row, *args):
                self.stopped_at[i] = {
                    "state": copy.deepcopy(row.state_dict()),
                    "frames": ev.frames[i],
                    "updates": ev.updates[i],
                    "seconds": time.perf_counter() - self.start,
                }
        return all(at is not None for at in self.stopped_at)

    def active(self) -> list[int]:
        """The seeds that have not stopped."""
        return [i for i, at in enumerate(self.stopped_at) if at is None]

    def finish(self, i: int) -> bool:
        """Seed ``i``'s row gets the weights it ends with: those it stopped with, else its best
        evaluated ones (:meth:`EarlyStop.restore_best`); returns whether those were restored."""
        at = self.stopped_at[i]
        if at is not None:
            self.rows[i].load_state_dict(at["state"])
            return False
        return self.monitors[i].restore_best(self.rows[i])

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
