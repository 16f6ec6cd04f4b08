"""When a loop stops and which weights it keeps, per seed (:class:`SeedEarlyStops`)."""

from __future__ import annotations

import copy
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from torchrl_stages.config import StageConfig
from torchrl_stages.learners import Learner
from torchrl_stages.learners.stacking import seed_axes


def can_stop_early(cfg: StageConfig) -> bool:
    """Whether an early stop can end a loop of ``cfg`` before its frame budget."""
    return (
        cfg.success_threshold is not None
        and int(cfg.eval_every) > 0
        and int(cfg.min_frames) <= int(cfg.frames)
    )


def first_evaluation(cfg: StageConfig) -> int:
    """Frames of a stage's first evaluation: ``eval_every``, or, with an early stop, the first of
    the ``patience`` evaluations that can stop the stage at ``min_frames``."""
    first = int(cfg.eval_every)
    if can_stop_early(cfg):
        first = max(first, int(cfg.min_frames) - (int(cfg.patience) - 1) * first)
    return first


@dataclass
class Evaluation:
    """One evaluation of every seed of a loop (one entry per seed)."""

    success: list[float]
    value_error: list[float]
    discounted_return: list[float | None]
    frames: list[int]
    updates: list[int]


@dataclass(eq=False)
class EarlyStop:
    """Stops after ``patience`` evaluations in a row meet the criterion past ``min_frames``; else
    :meth:`restore_best` puts back the best (most success, then ``keep_best_by``) weights."""

    cfg: StageConfig
    streak: int = 0
    stopped: bool = False
    best: tuple[float, float] | None = None  # (success, value error) of the best
    best_score: tuple[float, float] | None = None
    best_state: dict | None = None
    last: tuple[float, float] | None = None
    best_return: float | None = None  # mean discounted return of those evaluations
    last_return: float | None = None

    def record(
        self,
        learner: nn.Module,
        success: float,
        value_error: float,
        frames: int,
        ret: float | None = None,
    ) -> bool:
        """Records one evaluation (``ret``: its mean discounted return); whether to stop now."""
        cfg = self.cfg
        self.last, self.last_return = (success, value_error), ret
        score = (success, (ret or 0.0) if cfg.keep_best_by == "return" else -value_error)
        if cfg.keep_best and (self.best_score is None or score > self.best_score):
            self.best_score, self.best, self.best_return = score, (success, value_error), ret
            self.best_state = copy.deepcopy(learner.state_dict())
        met = (
            cfg.success_threshold is not None
            and success >= cfg.success_threshold
            and (cfg.value_tolerance is None or value_error <= cfg.value_tolerance)
        )
        self.streak = self.streak + 1 if met else 0
        self.stopped = self.streak >= cfg.patience and frames >= cfg.min_frames
        return self.stopped

    _FIELDS = "streak stopped best best_score best_state last best_return last_return".split()

    def state_dict(self) -> dict:
        return {f: getattr(self, f) for f in self._FIELDS}

    def load_state_dict(self, state: dict) -> None:
        for f in self._FIELDS:
            value = state.get(f) if f.endswith("_return") else state[f]
            setattr(self, f, tuple(value) if isinstance(value, list) else value)

    def restore_best(self, learner: nn.Module) -> bool:
        """Puts back the best evaluated weights; whether they differ from the loop's last ones."""
        if self.stopped or self.best_state is None:
            return False
        current = learner.state_dict()
        changed = any(not torch.equal(current[k], v) for k, v in self.best_state.items())
        if changed:
            learner.load_state_dict(self.best_state)
        return changed

    @property
    def final(self) -> tuple[float | None, float | None, float | None]:
        """(success, value error, discounted return) of the weights the stage ends with."""
        if self.stopped or self.best is None:
            return (*(self.last or (None, None)), self.last_return)
        return (*self.best, self.best_return)  # restore_best puts these weights back


class SeedRow:
    """Seed ``seed``'s row of a seed-stacked learner, or of every learner of a team (entries
    ``<m>.<key>``), as :class:`EarlyStop` reads and restores it (shared entries left alone).
    With ``moments``, a stop keeps the row's Adam moments too (the others' updates decay them).

    Examples:
        >>> from torchrl.data import Categorical
        >>> from torchrl_stages.learners import StageSpecs, make_learner
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> specs = StageSpecs(["observation"], 3, "action", Categorical(2, (1,)))
        >>> team = [make_learner(DQNConfig(num_cells=[8]), specs, seeds=2) for _ in range(2)]
        >>> state = SeedRow(team, 1).state_dict()  # learner 1's target network, seed 1's row
        >>> state["1.loss.target_value_network_params.module.0.module.value.2.weight"].shape
        torch.Size([1, 8])
    """

    def __init__(
        self, learners: Learner | Sequence[Learner], seed: int, moments: bool = False
    ) -> None:
        self.team = not isinstance(learners, nn.Module)
        self.learners = list(learners) if self.team else [learners]
        self.seed, self.keeps_moments = seed, moments
        self.axes = [
            {k: a for k, a in seed_axes(learner).items() if a is not None}
            for learner in self.learners
        ]

    def _rows(self, keep_vars: bool = False) -> Iterator[tuple[str, torch.Tensor]]:
        for m, (learner, axes) in enumerate(zip(self.learners, self.axes, strict=True)):
            state = learner.state_dict(keep_vars=keep_vars)
            for key, axis in axes.items():
                yield f"{m}.{key}" if self.team else key, state[key].data.select(axis, self.seed)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {entry: row.clone() for entry, row in self._rows()}

    @torch.no_grad()
    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        for entry, row in self._rows(keep_vars=True):
            if entry in state:
                row.copy_(state[entry])

    def moments(self, load: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """The row's Adam moments, copied out; with ``load`` (what this returned), written back."""
        out: dict[str, torch.Tensor] = {}
        for m, (learner, axes) in enumerate(zip(self.learners, self.axes, strict=True)):
            names = {id(p): n for n, p in learner.named_parameters(remove_duplicate=False)}
            for optimizer_name, optimizer in learner.optimizers.items():
                for param, state in optimizer.state.items():
                    name = names.get(id(param), "")
                    for key in ("exp_avg", "exp_avg_sq"):
                        if name not in axes or key not in state:
                            continue
                        row = state[key].select(axes[name], self.seed)
                        entry = f"{m}.{optimizer_name}.{name}.{key}"
                        if load is None:
                            out[entry] = row.clone()
                        elif entry in load:
                            row.copy_(load[entry])
        return out


def seed_rows(learners: Learner | Sequence[Learner], moments: bool = False) -> list[Any]:
    """What an early stop keeps and restores of each seed of a learner or a team of them."""
    one = isinstance(learners, nn.Module)
    seeds = (learners if one else learners[0]).seeds
    if seeds is None:
        return [learners if one else nn.ModuleList(learners)]
    return [SeedRow(learners, i, moments) for i in range(int(seeds))]


class SeedEarlyStops:
    """One :class:`EarlyStop` per seed of ``rows``; a seed that stops keeps its weights, frames,
    updates and seconds (:attr:`stopped_at`) while the others train on.

    Examples:
        >>> from torchrl_stages.learners.dqn import DQNConfig
        >>> cfg = DQNConfig(success_threshold=0.9, value_tolerance=None, patience=1)
        >>> stops = SeedEarlyStops(cfg, [nn.Linear(1, 1), nn.Linear(1, 1)])
        >>> stops.record(Evaluation([1.0, 0.5], [0.0, 0.0], [None, None], [64, 64], [8, 8]))
        False
        >>> stops.active(), stops.stopped_at[0]["frames"]
        ([1], 64)
    """

    def __init__(self, cfg: StageConfig, rows: Sequence[Any]) -> None:
        self.start = 0.0  # what stop times are measured from (time.perf_counter)
        self.cfg = cfg
        self.rows = list(rows)
        self.monitors = [EarlyStop(cfg) for _ in self.rows]
        self.stopped_at: list[dict | None] = [None] * len(self.rows)

    def record(self, evaluation: Evaluation) -> bool:
        """Whether every seed has stopped."""
        ev = evaluation
        for i in self.active():
            row = self.rows[i]
            args = (ev.success[i], ev.value_error[i], ev.frames[i], ev.discounted_return[i])
            if self.monitors[i].record(row, *args):
                at = {"state": copy.deepcopy(row.state_dict()), "frames": ev.frames[i]}
                at |= {"updates": ev.updates[i], "seconds": time.perf_counter() - self.start}
                if getattr(row, "keeps_moments", False):
                    at["moments"] = row.moments()
                self.stopped_at[i] = at
        return not self.active()

    def active(self) -> list[int]:
        """The seeds that have not stopped."""
        return [i for i, at in enumerate(self.stopped_at) if at is None]

    def finish(self, i: int) -> dict[str, Any]:
        """Seed ``i``'s row gets the weights it stopped with, else its best; their evaluation."""
        at, monitor, row = self.stopped_at[i], self.monitors[i], self.rows[i]
        if at is not None:
            row.load_state_dict(at["state"])
            if "moments" in at:
                row.moments(load=at["moments"])
        restored = monitor.restore_best(row)  # none after a stop
        keys = ("success_rate", "value_error", "discounted_return")
        ended = dict(zip(keys, monitor.final, strict=True))
        return ended | {"early_stopped": monitor.stopped, "restored_best": restored}

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
