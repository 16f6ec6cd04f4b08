"""Console scripts: ``stages-train`` (Hydra app) and ``stages-eval RUN_DIR``."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from omegaconf import DictConfig

from torchrl_stages.config import register_configs
from torchrl_stages.learners import Learner
from torchrl_stages.loggers import make_logger
from torchrl_stages.reports import evaluate_run, format_summary
from torchrl_stages.run import load_run, save_config, save_stage
from torchrl_stages.schedule import train_backward
from torchrl_stages.stage import DivergenceError, StageResult
from torchrl_stages.task import StagedTask
from torchrl_stages.validate import ConfigError, validate_config, validate_task

log = logging.getLogger("torchrl_stages")


def build_task(cfg: DictConfig) -> StagedTask:
    """Validates ``cfg`` and builds its task; raises :class:`ConfigError` before any training."""
    validate_config(cfg)
    try:
        task = StagedTask(cfg.task, device=cfg.device)
    except (InstantiationException, TypeError, ValueError, RuntimeError) as err:
        raise ConfigError(
            f"task.env: cannot build the env of task '{cfg.task.name}': {err}. "
            "Fix: check the task.env.* values (or task.env._target_)."
        ) from err
    validate_task(cfg, task)
    return task


def run_training(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Validates, trains every stage backward, evaluates; everything lands in ``run_dir``."""
    task = build_task(cfg)
    torch.set_num_threads(cfg.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    save_config(cfg, run_dir)
    logger = make_logger(cfg, run_dir)

    def on_stage_end(k: int, learner: Learner, result: StageResult) -> None:
        save_stage(run_dir, k, task.stage_names[k], learner, result)
        evaluated = result.success_rate is not None
        quality = (
            f"stage success {result.success_rate:.2f}, value error {result.value_error:.3f}"
            if evaluated
            else "not evaluated"
        )
        log.info(
            "stage %d (%s, %s): %d frames, %d updates, %.1fs, %s%s%s",
            k,
            task.stage_names[k],
            learner.algo,
            result.frames,
            result.updates,
            result.seconds,
            quality,
            " (early stop)" if result.early_stopped else "",
            " (best evaluation restored)" if result.restored_best else "",
        )

    start = time.perf_counter()
    learners, results = train_backward(
        task, seed=cfg.seed, logger=logger, progress=cfg.progress, on_stage_end=on_stage_end
    )
    training = {"seconds": time.perf_counter() - start, "stages": [asdict(r) for r in results]}
    result = evaluate_run(cfg, task, learners, run_dir, training=training)
    if logger is not None:
        for key in ("success_rate", "mean_return", "mean_steps"):
            logger.log_scalar(f"eval/task/{key}", result[key], step=0)
    return result


@hydra.main(config_path="pkg://torchrl_stages.conf", config_name="config", version_base="1.3")
def _train_app(cfg: DictConfig) -> float:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        result = run_training(cfg, run_dir)
    except ConfigError as err:
        print(f"stages-train: invalid config: {err}", file=sys.stderr)
        sys.exit(2)
    except DivergenceError as err:
        print(f"stages-train: {err}", file=sys.stderr)
        sys.exit(3)
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
        help="whole-task episodes (default: the run's eval.episodes)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        run = load_run(args.run_dir)
    except FileNotFoundError as err:
        print(f"stages-eval: {err}", file=sys.stderr)
        sys.exit(2)
    if args.episodes is not None:
        run.cfg.eval.episodes = args.episodes
    if args.no_plots:
        run.cfg.eval.plots = False
    training = {"stages": run.results}
    result = evaluate_run(run.cfg, run.task, run.learners, args.run_dir, training=training)
    print(format_summary(result, args.run_dir))
