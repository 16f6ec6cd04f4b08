"""A training launch, the library API behind ``stages-train``: one seed, or several at once."""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from torchrl_stages.checkpoint import StageCheckpoints
from torchrl_stages.config import ConfigError, check
from torchrl_stages.learners import make_learner
from torchrl_stages.loggers import Observer
from torchrl_stages.preemption import handle_signals
from torchrl_stages.runs.directory import drop_checkpoints, refuse_links, scope_checkpoints
from torchrl_stages.runs.evaluation import format_summary
from torchrl_stages.runs.layout import SEED_CHECKPOINTS, seed_dir
from torchrl_stages.runs.seed_run import SeedRun, build_task, compile_mode
from torchrl_stages.schedules import SCHEDULES, get_schedule
from torchrl_stages.sweeps import summarize_or_say
from torchrl_stages.task import StagedTask
from torchrl_stages.threads import hold_threads


def validate_seeds(cfg: DictConfig) -> list[int]:
    """``cfg.seeds`` as ints; :class:`ConfigError` when they cannot train in one process."""
    raw = cfg.get("seeds")
    shown = OmegaConf.to_container(raw) if isinstance(raw, ListConfig) else raw
    listed = isinstance(raw, ListConfig | list) and len(raw) > 0
    check(listed, "seeds", shown, "must be a non-empty list of seeds", "seeds=[0,1,2]")
    ok = all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in raw)
    check(ok, "seeds", shown, "every seed must be an int >= 0", "seeds=[0,1,2]")
    seeds = [int(s) for s in raw]
    once = f"seeds=[{','.join(str(s) for s in dict.fromkeys(seeds))}]"
    check(len(set(seeds)) == len(seeds), "seeds", shown, "a seed is listed twice", once)
    name = str(cfg.schedule.name)
    able = [n for n, schedule in SCHEDULES.items() if schedule.stacks_seeds]
    check(
        get_schedule(name).stacks_seeds,
        "seeds",
        shown,
        f"schedule={name} cannot train several seeds in one process yet ({', '.join(able)} can)",
        f"schedule={'|'.join(able)}, or train the seeds apart: stages-train -m "
        f"schedule={name} seed={','.join(str(s) for s in seeds)}",
    )
    probe = "the whole-task probe is not run for several seeds in one process"
    check(not cfg.eval.get("probe", False), "eval.probe", True, probe, "eval.probe=false")
    return seeds


def check_stackable(task: StagedTask, num_seeds: int) -> None:
    """Raises :class:`ConfigError` naming the stage that cannot stack ``num_seeds`` seeds."""
    for k, name in enumerate(task.stage_names):
        try:
            make_learner(task.stage_cfg(k), task.specs(k), seeds=num_seeds)
        except ConfigError as err:
            raise ConfigError(f"task.stages.{name}: {err}") from None
        except TypeError as err:
            raise ConfigError(
                f"task.stages.{name}: its networks cannot be stacked for seeds: {err}. Fix: "
                "train its seeds apart (stages-train -m seed=0,1,2)"
            ) from None


def _for_seed(
    cfg: DictConfig, seed: int, files: dict[str, Any] | None = None
) -> tuple[DictConfig, dict[str, Any] | None]:
    """Seed ``seed``'s config and ``.hydra/`` files (the sweep summary groups seeds by their
    ``seed=`` override)."""
    out = copy.deepcopy(cfg)
    with open_dict(out):
        out.seed, out.seeds = seed, None
    if not files:
        return out, files
    overrides = [str(o) for o in files.get("overrides.yaml", [])]
    kept = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in ("seeds", "seed")]
    return out, {**files, "config.yaml": out, "overrides.yaml": [*kept, f"seed={seed}"]}


class Experiment:
    """Trains and evaluates ``cfg`` in ``run_dir``; with ``cfg.seeds``, every seed at once
    (networks stacked) in ``<run_dir>/seed_<s>/``. SIGTERM, SIGINT and SIGUSR1 stop it at the
    next batch with a checkpoint.

    Examples:
        >>> from hydra import compose, initialize_config_module
        >>> from torchrl_stages.config import register_configs
        >>> from torchrl_stages.learners import ALGORITHMS
        >>> register_configs(ALGORITHMS)
        >>> with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
        ...     cfg = compose("config", overrides=["experiment=smoke", "seeds=[0,1]"])
        >>> results = Experiment(cfg, "runs/grid_seeds").run()  # doctest: +SKIP
        >>> [r["success_rate"] for r in results]  # doctest: +SKIP
        [1.0, 1.0]
    """

    def __init__(
        self,
        cfg: DictConfig,
        run_dir: str | Path,
        *,
        hydra_files: dict[str, Any] | None = None,
        observers: Sequence[Observer] = (),
    ) -> None:
        self.stacked = cfg.get("seeds") is not None
        self.seeds = validate_seeds(cfg) if self.stacked else [int(cfg.seed)]
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.checkpoint_root = self.run_dir / SEED_CHECKPOINTS  # several seeds' loops: one state
        self.runs: list[SeedRun] = []
        if not self.stacked:
            self.runs.append(SeedRun(cfg, self.run_dir, hydra_files, observers))
            return
        # before any directory is made: the config, and whether it stacks
        task = build_task(_for_seed(cfg, self.seeds[0])[0])  # the seeds' task, built once
        check_stackable(task, len(self.seeds))
        try:
            for seed in self.seeds:
                seed_cfg, files = _for_seed(cfg, seed, hydra_files)
                path = seed_dir(self.run_dir, seed)
                self.runs.append(SeedRun(seed_cfg, path, files, observers, seed=seed, task=task))
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for run in self.runs:
            run.close()

    def run(self) -> list[dict[str, Any]]:
        """Trains what is left and evaluates: each seed's ``eval.json``."""
        cfg = self.runs[0].cfg
        try:
            with handle_signals(), hold_threads(int(cfg.threads)):
                try:
                    results = self._run()
                except Exception as err:  # recorded before a launcher's handler runs
                    for run in self.runs:
                        run.ended(err)
                    raise
        finally:
            self.close()
        if self.stacked:  # best effort: the runs are written
            failure = f"the summary of {self.run_dir} was not written"
            summarize_or_say(self.run_dir, bool(cfg.eval.get("plots", True)), failure)
        return results

    def report(self, results: list[dict[str, Any]]) -> float:
        """Prints each seed's summary; returns their mean ``objective.metric`` (NaN fails a
        trial)."""
        for seed, result in zip(self.seeds, results, strict=True):
            where = seed_dir(self.run_dir, seed) if self.stacked else self.run_dir
            print(format_summary(result, where), flush=True)
        values = [result.get(self.cfg.objective.metric, float("nan")) for result in results]
        return sum(map(float, values)) / len(values)

    def _run(self) -> list[dict[str, Any]]:
        runs, cfg = self.runs, self.runs[0].cfg
        for run in runs:
            run.start()
        # several seeds' stacked networks train uncompiled: compiling them is unmeasured
        compile = "off" if self.stacked else compile_mode(cfg)
        if compile != "off":
            # compiled code starts fresh in every run: the jobs of a sweep run one after another
            # in one process, and their learners' recompiles would add up to Dynamo's limit
            torch._dynamo.reset()
        trained = runs[0].schedule.train(
            runs[0].task,
            self.seeds,
            keepers=runs,
            logs=[run.log for run in runs],
            checkpoints=self._checkpoints(),
            progress=bool(cfg.progress),
            probe=runs[0].probe(),  # None for several seeds: validate_seeds refuses eval.probe
            compile=compile,
        )
        if self.stacked:
            drop_checkpoints(self.checkpoint_root)
            for one in trained:  # eval.json: its wall-clock is that of all of them
                one.extra["trained_with_seeds"] = list(self.seeds)
        return [run.finish(one) for run, one in zip(runs, trained, strict=True)]

    def _checkpoints(self) -> Callable[[int | str], StageCheckpoints]:
        """One seed's checkpoints; several seeds' per scope, kept only when every seed resumes."""
        root, first = self.checkpoint_root, self.runs[0]
        if not self.stacked:
            return partial(first.run_dir.checkpoints, cfg=first.cfg)
        refuse_links([root])
        if not all(run.resuming for run in self.runs):
            drop_checkpoints(root, every=True)
        at = partial(scope_checkpoints, root, cfg=first.cfg)
        for stage in first.restarted:  # resumed stages whose config changed
            at(first.schedule.checkpoint_scope(stage)).clear()
        return at
