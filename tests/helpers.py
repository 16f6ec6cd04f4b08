"""Helpers the tests share: configs composed in-process, tiny budgets, console scripts run as
subprocesses, and figure checks. Fixtures are in ``conftest.py``."""

from __future__ import annotations

import ast
import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

from cli_server import shared_server
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config import register_configs, validate_config
from torchrl_stages.learners import ALGORITHMS, learner_class
from torchrl_stages.schedules import get_schedule
from torchrl_stages.task import StagedTask


def assert_figure(path: Path, min_side: int = 200) -> None:
    """Asserts that ``path`` is a PNG of at least ``min_side`` pixels a side that is not blank."""
    from matplotlib import image

    path = Path(path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    pixels = image.imread(path)
    height, width = pixels.shape[:2]
    assert min(height, width) >= min_side, f"{path} is {width} x {height} pixels"
    assert float(pixels.std()) > 0.01, f"{path} is blank"


@contextlib.contextmanager
def hydra_config(*base: str) -> Iterator[Callable[..., DictConfig]]:
    """Yields ``compose(*overrides)`` of the root config (``base`` overrides first), with
    Hydra initialised from a cleared global state and cleared again on exit."""
    GlobalHydra.instance().clear()
    register_configs(ALGORITHMS)
    try:
        with initialize_config_module("torchrl_stages.conf", version_base="1.3"):
            yield lambda *overrides: compose("config", overrides=[*base, *overrides])
    finally:
        GlobalHydra.instance().clear()


def validate(cfg: DictConfig) -> None:
    """``validate_config`` with the schedule ``cfg`` names and the package's learners."""
    validate_config(cfg, get_schedule(str(cfg.schedule.name)), learner_class, ALGORITHMS)


TINY_STAGE = {  # per-stage budgets that train any stage in about a second
    "frames": 256,
    "frames_per_batch": 128,
    "num_envs": 16,
    "init_random_frames": 128,
    "batch_size": 32,
    "updates_per_batch": 1,
    "eval_every": 128,
    "eval_episodes": 4,
    "min_frames": 0,
}


def tiny_grid(stage: dict | None = None) -> list[str]:
    """Overrides of a two-stage 10 x 10 grid world whose two stages train on ``stage``'s keys
    (default :data:`TINY_STAGE`), without figures or progress bars."""
    keys = TINY_STAGE if stage is None else stage
    return [
        "task.env.size=10",
        "task.env.num_stages=2",
        *[f"~task.stages.s{k}" for k in (2, 3, 4)],
        *[f"task.stages.s{k}.{key}={value}" for k in (0, 1) for key, value in keys.items()],
        "eval.plots=false",
        "progress=false",
    ]


def console_script(name: str) -> str:
    """The installed console script ``name`` (next to this interpreter if not on PATH)."""
    found = shutil.which(name)
    path = Path(found) if found else Path(sys.executable).parent / name
    assert path.is_file(), f"console script {name} not found (is the package installed?)"
    return str(path)


def cli_env(**extra: str) -> dict[str, str]:
    """The environment of a CLI subprocess: one thread, Hydra's short error messages."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", **extra)
    env.pop("HYDRA_FULL_ERROR", None)
    return env


class Launched:
    """A console script (``argv[0]``: its name or path) started in the background; its
    :meth:`result` waits for it. It runs in a fork of a process that has imported the package
    (``cli_server``: the script's argv, directory, environment, output and exit status,
    without its import); several run at the same time, as background processes would.

    The fork is a process of its own (:attr:`pid`): :meth:`send_signal`, :meth:`poll` and
    :meth:`communicate` work as :class:`subprocess.Popen`'s do, so signal and kill tests run
    without the import too. ``file_size_limit``: no file it writes may grow past that many
    bytes (``RLIMIT_FSIZE``), for tests of a full disk."""

    def __init__(
        self,
        argv: list,
        cwd: Path,
        timeout: float = 300,
        *,
        file_size_limit: int | None = None,
        **env: str,
    ) -> None:
        console_script(argv[0])  # installed
        self.args = [Path(argv[0]).name, *(str(a) for a in argv[1:])]
        self.server = shared_server()
        self.job = self.server.start(self.args, Path(cwd), cli_env(**env), timeout, file_size_limit)
        self.pid = self.server.pid(self.job)
        self._result: subprocess.CompletedProcess | None = None

    def result(self) -> subprocess.CompletedProcess:
        """The finished command (:class:`subprocess.TimeoutExpired` past its timeout)."""
        if self._result is None:
            self._result = self.server.wait(self.job)
        return self._result

    def stop(self) -> None:
        """Kills it if it still runs and nothing waited for it."""
        if self._result is None:
            self.server.kill(self.job)

    @property
    def returncode(self) -> int | None:
        return None if self._result is None else self._result.returncode

    def poll(self) -> int | None:
        """Its exit status if it has ended, else None (without waiting)."""
        if self._result is None and self.server.finished(self.job):
            self.result()
        return self.returncode

    def send_signal(self, signum: int) -> None:
        """Sends ``signum`` to the command's process, if it still runs."""
        if self.poll() is None:
            os.kill(self.pid, signum)

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        """Waits for it (its own timeout applies); its ``(stdout, stderr)``."""
        result = self.result()
        return result.stdout, result.stderr


def run_cli(argv: list, cwd: Path, timeout: float = 300, **env: str) -> subprocess.CompletedProcess:
    """Runs a console script (``argv[0]``: its name or path) to completion (:class:`Launched`)."""
    return Launched(argv, cwd, timeout, **env).result()


def run_script(
    script: Path, *args: object, cwd: Path | None = None, timeout: float = 300, **env: str
) -> subprocess.CompletedProcess:
    """``python <script> args`` to completion, in ``cwd`` (default: this one) with this
    process's environment and ``env``: run as ``__main__`` in a fork of a process that has
    imported the package (``cli_server``), as :class:`Launched` runs the console scripts."""
    argv = [str(script), *(str(a) for a in args)]
    directory = Path.cwd() if cwd is None else Path(cwd)
    return shared_server().run(argv, directory, {**os.environ, **env}, timeout)


def docstring_ids(tree: ast.AST) -> set[int]:
    """The ``id`` of every docstring constant of a parsed module (module, classes, functions):
    what checks of a module's code leave out."""
    return {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }


def two_stage_grid(a, b=None, size: int = 10, **env) -> StagedTask:
    """A two-stage ``size`` x ``size`` grid world task whose stages ``a`` and ``b`` (default:
    ``a``'s) are stage configs (dataclasses or dicts)."""
    return StagedTask(
        OmegaConf.create(
            {
                "name": "grid",
                "stages": {"a": a, "b": a if b is None else b},
                "env": {
                    "_target_": "torchrl_stages.envs.GridWorldEnv",
                    "size": size,
                    "num_stages": 2,
                    **env,
                },
            }
        )
    )
