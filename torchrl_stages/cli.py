"""The console scripts ``stages-train``, ``-tune``, ``-eval``, ``-report`` and ``-store``. Exit
codes: 0 done, 1 failed, 2 invalid config, refused directory or unwritable file, 3 diverged,
128 + N stopped by signal N with a checkpoint."""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import re
import sys
import time
import traceback
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any, NoReturn

import hydra
import torch
from hydra._internal.utils import get_args_parser
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_stages.callbacks import RunDirCallback
from torchrl_stages.checkpoint import CheckpointDamagedError
from torchrl_stages.config import ConfigError, apply_all_stages, register_configs, stage_keys_set
from torchrl_stages.config.checks import validate_sweeper
from torchrl_stages.config.registration import hydra_message
from torchrl_stages.failures import (
    EXIT_DIVERGED,
    EXIT_FAILED,
    EXIT_INVALID,
    DivergenceError,
    EnvError,
    one_line,
)
from torchrl_stages.gym_env import SuccessKeyError
from torchrl_stages.integrity import DamagedFileError
from torchrl_stages.learners import ALGORITHMS
from torchrl_stages.preemption import Interrupted
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.evaluation import evaluate_run, format_summary
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.loading import load_run
from torchrl_stages.runs.seed_run import with_env_stages
from torchrl_stages.runs.stage_store import SharedStageStore, StageEntry, StoreError
from torchrl_stages.sweeps import find_jobs, summarize_sweep
from torchrl_stages.tune import StudyContext, StudyError, run_study


class JobFailed(RuntimeError):
    """A multirun job that failed; its directory's ``status.json`` says why."""


def _exit(prog: str, message: str, code: int = EXIT_INVALID) -> NoReturn:
    print(f"{prog}: {message}", file=sys.stderr)
    sys.exit(code)


def _hydra_files(cfg: DictConfig) -> dict[str, Any]:
    """What Hydra would write to ``.hydra/`` (the run writes it: ``output_subdir`` is off)."""
    hydra_cfg = HydraConfig.get()
    return {
        "config.yaml": cfg,
        "hydra.yaml": OmegaConf.create({"hydra": hydra_cfg}),
        "overrides.yaml": hydra_cfg.overrides.task,
    }


def _fail(run_dir: Path, message: str, code: int, status: str | None = None) -> NoReturn:
    """Reports a failed job in one line; in a multirun it raises, so the sweep goes on."""
    if HydraConfig.get().mode == RunMode.MULTIRUN:
        print(f"stages-train: {message}", file=sys.stderr)
        if status is not None:
            RunDir(run_dir).write_status(status, message)
        raise JobFailed(f"{run_dir}: {message}")
    if code == EXIT_INVALID:
        RunDirCallback.remove_made(run_dir)
    _exit("stages-train", message, code)


@hydra.main(config_path="pkg://torchrl_stages.conf", config_name="config", version_base="1.3")
def _train_app(cfg: DictConfig) -> float:
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    try:
        if multirun:  # a sweeper that optimizes must optimize the objective's direction
            validate_sweeper(hydra_cfg.sweeper, cfg)
        # all_stages (experiment=smoke) in every stage, but not over a stage's own override
        cfg = apply_all_stages(cfg, keep=stage_keys_set(hydra_cfg.overrides.task))
        experiment = Experiment(cfg, run_dir, hydra_files=_hydra_files(cfg))
    except ConfigError as err:
        if multirun:  # the job's own fresh directory: the sweep summary shows why
            RunDir(run_dir).write_hydra_files(_hydra_files(cfg))
        _fail(run_dir, f"invalid config: {err}", EXIT_INVALID, status="invalid")
    except (RunDirError, OSError) as err:  # RunDirError: another run's directory, left as it was
        _fail(run_dir, _reason(err, run_dir), EXIT_INVALID)
    try:  # how a run that does not finish ended is in its status.json (Experiment.run)
        results = experiment.run()
    except Interrupted as err:
        fix = f"Fix: continue it with the same command and resume=true (hydra.run.dir={run_dir})"
        _exit("stages-train", f"{err}; what it needs to continue is written. {fix}", err.exit_code)
    except DivergenceError as err:
        _fail(run_dir, str(err), EXIT_DIVERGED)
    except (RunDirError, CheckpointDamagedError, DamagedFileError, OSError) as err:
        _fail(run_dir, _reason(err, run_dir), EXIT_INVALID)
    except (EnvError, SuccessKeyError) as err:
        _fail(run_dir, str(err), EXIT_FAILED)
    except Exception as err:  # the env's (or other user code's) own exception: its traceback
        traceback.print_exc()
        _fail(run_dir, one_line(err), EXIT_FAILED)
    objective = experiment.report(results)  # over seeds: their mean
    if experiment.stacked:
        print(f"Seeds' summary: {run_dir}")  # what summarize_sweep wrote over them
        for path in sorted(run_dir.glob("summary*")):
            print(f"  {path.name}: {path}")
    return objective


def _reason(err: Exception, run_dir: Path) -> str:
    """``err``'s message; for an ``OSError``, what could not be written and how to fix it."""
    if not isinstance(err, OSError):
        return str(err)
    return (
        f"cannot write {err.filename or run_dir}: {err.strerror or err}. Fix: free space on that "
        "disk or make it writable, then rerun with resume=true (or pick another hydra.run.dir)"
    )


@contextlib.contextmanager
def hydra_refusals(prog: str) -> Iterator[None]:
    """Hydra's own refusals (an unknown key or group option, a value of the wrong type, an
    override it cannot parse, a directory it cannot make) in one line with exit 2, as the
    package's own; ``HYDRA_FULL_ERROR=1`` keeps Hydra's report."""
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises what it would print
    try:
        yield
    except (HydraException, OmegaConfBaseException) as err:
        fix = f"Fix: `{prog} --cfg job` lists the keys and values, `{prog} --help` the options"
        _exit(prog, f"invalid config: {hydra_message(err)}. {fix}")
    except OSError as err:  # Hydra makes the run directory before the job starts
        _exit(prog, _reason(err, Path(err.filename or ".")))
    except JobFailed as err:  # a multirun's failed job, said once it ended (its status.json)
        _exit(prog, str(err), EXIT_FAILED)
    finally:
        del os.environ["HYDRA_FULL_ERROR"]


def train() -> None:
    """``stages-train [OVERRIDES...]``: train a task (Hydra CLI)."""
    register_configs(ALGORITHMS)
    with hydra_refusals("stages-train"):
        if get_args_parser().parse_known_args(sys.argv[1:])[0].cfg not in ("job", "all"):
            _train_app()
            return
        shown = io.StringIO()  # --cfg job|all: Hydra's YAML, with the stages of a template task
        try:
            with contextlib.redirect_stdout(shown):
                _train_app()
        finally:
            sys.stdout.write(with_template_stages(shown.getvalue()))


def with_template_stages(text: str) -> str:
    """``--cfg job``'s YAML with ``task.stages`` made from ``task.stage_template``, or, where the
    env cannot be built, a comment on ``stages:`` saying why."""
    try:
        cfg = OmegaConf.create(text)
        if not OmegaConf.select(cfg, "task.stage_template"):
            return text
    except Exception:  # noqa: BLE001 - not one YAML document (--package, a value): as given
        return text
    try:
        return OmegaConf.to_yaml(with_env_stages(cfg))
    except Exception as err:  # noqa: BLE001 - the env's own error, said on the stages line
        reason = str(err) if isinstance(err, ConfigError) else one_line(err)
    note = (
        "  # made from the env: s0, s1, ... for its num_stages, each task.stage_template with "
        f"its own task.stages.s<k> keys over it; listed once the env can be built ({reason})"
    )
    stages = re.compile(r"^task:\n(?:[ \t].*\n|\n)*?  stages:.*$", re.M)
    return stages.sub(lambda block: block[0] + " ".join(note.splitlines()), text, count=1)


@hydra.main(config_path="pkg://torchrl_stages.conf", config_name="tune", version_base="1.3")
def tune_app(cfg: DictConfig) -> None:
    """Exit codes: 0 done, 1 every trial failed, 2 invalid config or a study that cannot go on,
    128 + N stopped by signal N."""
    hydra_cfg = HydraConfig.get()
    context = StudyContext(
        study_dir=Path(hydra_cfg.runtime.output_dir),
        cwd=Path(hydra_cfg.runtime.cwd),
        overrides=list(hydra_cfg.overrides.task),
        compose=partial(hydra.compose, "config"),
        hydra_cfg=hydra_cfg,
    )
    try:
        code = run_study(cfg, context)
    except ConfigError as err:
        _exit("stages-tune", f"invalid config: {err}")
    except StudyError as err:
        _exit("stages-tune", str(err))
    except Interrupted as err:
        fix = "Fix: run the same command again to go on with the study"
        _exit("stages-tune", f"{err}; the trial is recorded as failed. {fix}", err.exit_code)
    if code:
        _exit("stages-tune", "every trial failed (their status.json say why)", code)


def tune() -> None:
    """``stages-tune [OVERRIDES...]``: an Optuna study of ``stages-train`` runs (Hydra CLI)."""
    register_configs(ALGORITHMS)
    with hydra_refusals("stages-tune"):
        tune_app()


def evaluate(argv: list[str] | None = None) -> None:
    """``stages-eval RUN_DIR``: re-evaluate a finished run and rewrite its ``eval.json``."""
    parser = argparse.ArgumentParser(prog="stages-eval", description=evaluate.__doc__)
    parser.add_argument("run_dir", type=Path, help="a run directory written by stages-train")
    parser.add_argument(
        "--episodes",
        type=int,
        help="whole-task episodes from random starts (default: the run's eval.episodes; "
        "envs that enumerate their starts are evaluated from each one)",
    )
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    parser.add_argument(
        "--trust",
        action="store_true",
        help="load a run whose config names code of its own (task=gym, task=custom, a config "
        "directory of yours): its env is imported and called. Only for runs you made or checked",
    )
    args = parser.parse_args(argv)
    if args.episodes is not None and args.episodes < 1:
        parser.error(f"argument --episodes: must be a positive integer, got {args.episodes}")
    torch.set_num_threads(1)
    directory = RunDir(args.run_dir)
    with contextlib.ExitStack() as stack:
        try:
            if directory.holds_run():  # a second process would write the same files
                stack.enter_context(directory.lock()).announce()  # named to a process it refuses
            run = load_run(args.run_dir, trust=args.trust)
            if args.episodes is not None:
                run.cfg.eval.episodes = args.episodes
            if args.no_plots:
                run.cfg.eval.plots = False
            training = (directory.read_eval() or {}).get("training")
            if not isinstance(training, dict):  # rebuilt from what the run directory keeps
                training = {**directory.training_time(), "stages": run.results}
            before = directory.listing()
            result = evaluate_run(run.cfg, run.task, run.learners, args.run_dir, training=training)
            if directory.has_record():
                directory.claim_new(before)
        except (RunDirError, OSError) as err:
            _exit("stages-eval", _reason(err, args.run_dir))
    print(format_summary(result, args.run_dir))


def report(argv: list[str] | None = None) -> None:
    """``stages-report SWEEP_DIR``: (re)write the summary of a directory of runs."""
    parser = argparse.ArgumentParser(
        prog="stages-report",
        description="Summarize a directory of stages-train runs (a sweep directory, or runs "
        "gathered by hand): writes summary.csv, summary_configs.csv, summary.md (mean and IQM "
        "across seeds, with 95%% confidence intervals) and summary_*.png into it.",
    )
    parser.add_argument("sweep_dir", type=Path, help="the sweep directory (hydra.sweep.dir)")
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    parser.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default 0)")
    args = parser.parse_args(argv)
    directory: Path = args.sweep_dir
    if not directory.is_dir():
        _exit("stages-report", f"{directory} is not a directory")
    if not find_jobs(directory):
        _exit(
            "stages-report",
            f"no job directory under {directory} (a job directory holds .hydra/overrides.yaml, "
            "eval.json, status.json or config.yaml). Fix: pass the sweep directory of a "
            "`stages-train -m` run (hydra.sweep.dir)",
        )
    summary = summarize_sweep(directory, plots=not args.no_plots, seed=args.seed)
    for agg in summary.aggregates:
        if agg.metric == "success_rate":
            mean = "-" if agg.mean is None else f"{agg.mean:.3f}"
            ci = "" if agg.ci_low is None else f" [{agg.ci_low:.3f}, {agg.ci_high:.3f}]"
            print(f"{agg.config}: success {mean}{ci} over {agg.n} seeds, {agg.failed} failed")
    for name, path in summary.files.items():
        print(f"{name}: {path}")


def _age(text: str) -> float:
    """``30d``, ``12h``, ``90m`` or seconds, as seconds."""
    scale = {"d": 86400.0, "h": 3600.0, "m": 60.0, "s": 1.0}.get(text[-1:])
    try:
        return float(text[:-1]) * scale if scale else float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an age such as 30d, 12h or 90m: {text!r}") from None


def stage_store(argv: list[str] | None = None) -> None:
    """``stages-store ls|rm|prune DIR``: list, remove and prune the entries of a stage store."""
    parser = argparse.ArgumentParser(
        prog="stages-store",
        description="Manage a stage store (stages-train stage_store=DIR): the finished stages "
        "that runs share, one entry per stage identity.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    ls = commands.add_parser("ls", help="list the entries, least recently used first")
    ls.add_argument("store", type=Path)
    rm = commands.add_parser("rm", help="remove entries by (a prefix of) their identity")
    rm.add_argument("store", type=Path)
    rm.add_argument("identity", nargs="+", help="identity or a unique prefix of it")
    prune = commands.add_parser(
        "prune",
        help="remove damaged entries, what interrupted writes left, locks nobody holds and "
        "(with --older-than) entries not used for that long",
    )
    prune.add_argument("store", type=Path)
    prune.add_argument("--older-than", type=_age, default=None, help="e.g. 30d, 12h, 90m")
    prune.add_argument("--dry-run", action="store_true", help="list what would be removed")
    args = parser.parse_args(argv)
    if not (args.store / "entries").is_dir():
        _exit(
            "stages-store",
            f"{args.store} is not a stage store (no entries/ in it). Fix: pass the directory "
            "given to stages-train as stage_store=DIR",
        )
    store = SharedStageStore(args.store)
    try:
        if args.command == "ls":
            print(format_entries(store.entries()))
        elif args.command == "rm":
            for prefix in args.identity:
                print(f"removed {store.remove(prefix)}")
        else:
            removed = store.prune(args.older_than, dry_run=args.dry_run)
            verb = "would remove" if args.dry_run else "removed"
            for path in removed:
                print(f"{verb} {path}")
            print(f"{verb} {len(removed)} item(s)")
    except StoreError as err:
        _exit("stages-store", str(err))


def format_entries(entries: list[StageEntry]) -> str:
    """The table ``stages-store ls`` prints."""
    rows = [
        "identity      task        stage  algo          seed    frames  success  size     last used"
    ]
    for e in entries:
        used = time.strftime("%Y-%m-%d %H:%M", time.localtime(e.last_used))
        success = "-" if e.success_rate is None else f"{e.success_rate:.2f}"
        stage = f"{e.stage} {e.name}"
        line = (
            f"{e.identity[:12]:<13} {e.task[:11]:<11} {stage[:6]:<6} {e.algo[:13]:<13} "
            f"{e.seed:<7} {e.frames:<7} {success:<8} {e.size / 2**20:5.1f}MiB  {used}"
        )
        rows.append(line + (f"  DAMAGED: {e.damaged}" if e.damaged else ""))
    rows.append(f"{len(entries)} entries, {sum(e.size for e in entries) / 2**20:.1f} MiB")
    return "\n".join(rows)
