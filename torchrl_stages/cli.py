"""Console scripts: ``stages-train`` (Hydra app) and ``stages-eval RUN_DIR``.

Both are thin shells over the library: :class:`torchrl_stages.experiment.Experiment` trains,
:func:`torchrl_stages.rundir.load_run` and :func:`torchrl_stages.reports.evaluate_run`
re-evaluate. Exit codes: 0 done, 2 invalid config or run directory, 3 training diverged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config import register_configs
from torchrl_stages.experiment import Experiment
from torchrl_stages.reports import evaluate_run, format_summary
from torchrl_stages.rundir import RunDir, RunDirError, load_run
from torchrl_stages.stage import DivergenceError
from torchrl_stages.validate import ConfigError

EXIT_INVALID, EXIT_DIVERGED = 2, 3


class JobFailed(RuntimeError):
    """A multirun job that failed; its directory's ``status.json`` says why."""


def _write_hydra_files(cfg: DictConfig, run_dir: Path) -> None:
    """What Hydra writes to ``.hydra/`` (its ``output_subdir`` is off, see ``conf/config.yaml``):
    the composed config, Hydra's config and the command-line overrides."""
    hydra_cfg = HydraConfig.get()
    out = run_dir / ".hydra"
    out.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, out / "config.yaml")
    OmegaConf.save(OmegaConf.create({"hydra": hydra_cfg}), out / "hydra.yaml")
    OmegaConf.save(hydra_cfg.overrides.task, out / "overrides.yaml")


def _fail(run_dir: Path, status: str, message: str, code: int, write_status: bool) -> None:
    """Reports a failed job: one line on stderr; in a multirun, ``status.json`` in its
    directory and an exception, so the sweep goes on with the other jobs and exits non-zero."""
    print(f"stages-train: {message}", file=sys.stderr)
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    if multirun or write_status:
        RunDir(run_dir).write_status(status, message)
    if multirun:
        raise JobFailed(f"{run_dir}: {message}")
    sys.exit(code)


@hydra.main(config_path="pkg://torchrl_stages.conf", config_name="config", version_base="1.3")
def _train_app(cfg: DictConfig) -> float:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    try:
        experiment = Experiment(cfg, run_dir)
    except RunDirError as err:  # the directory holds another run: touch nothing there
        _fail(run_dir, "refused", str(err), EXIT_INVALID, write_status=False)
    except ConfigError as err:
        if multirun:
            _write_hydra_files(cfg, run_dir)
        _fail(run_dir, "invalid", f"invalid config: {err}", EXIT_INVALID, write_status=False)
    if not experiment.resuming:
        _write_hydra_files(cfg, run_dir)
    try:
        result = experiment.run()
    except DivergenceError as err:
        _fail(run_dir, "diverged", str(err), EXIT_DIVERGED, write_status=True)
    except RunDirError as err:
        _fail(run_dir, "failed", str(err), EXIT_INVALID, write_status=True)
    print(format_summary(result, run_dir))
    return float(result["success_rate"])  # the objective of sweeper plugins (e.g. Optuna)


def train() -> None:
    """``stages-train [OVERRIDES...]``: train a task with the backward schedule (Hydra CLI)."""
    register_configs()
    _train_app()


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def evaluate(argv: list[str] | None = None) -> None:
    """``stages-eval RUN_DIR``: re-evaluate a finished run and rewrite its ``eval.json``."""
    parser = argparse.ArgumentParser(prog="stages-eval", description=evaluate.__doc__)
    parser.add_argument("run_dir", type=Path, help="a run directory written by stages-train")
    parser.add_argument(
        "--episodes",
        type=_positive_int,
        default=None,
        help="whole-task episodes from random starts (default: the run's eval.episodes; "
        "envs that enumerate their starts are evaluated from each one)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        run = load_run(args.run_dir)
    except RunDirError as err:
        print(f"stages-eval: {err}", file=sys.stderr)
        sys.exit(EXIT_INVALID)
    if args.episodes is not None:
        run.cfg.eval.episodes = args.episodes
    if args.no_plots:
        run.cfg.eval.plots = False
    training = {"stages": run.results}
    result = evaluate_run(run.cfg, run.task, run.learners, args.run_dir, training=training)
    print(format_summary(result, args.run_dir))
