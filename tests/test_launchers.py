"""Sweeps beyond the basic launcher, through the optional extras: submitit's local launcher
(``[submit]``, the SLURM launcher's local twin) and Ray (``[ray]``, a local Ray instance that
the launcher's ``ray.init`` starts inside ``stages-train`` and that stops when it exits). Each
test is skipped, with the reason, only when its extra is not installed
(``pip install -e ".[submit,ray]"``); CI installs ``[test]`` only. Optuna studies are
``stages-tune``'s (``tests/test_tune.py``).

Every sweep is ``experiment=smoke``; the commands start together when the module's first test
runs and each test waits for its own.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
from pathlib import Path

import pytest
from helpers import cli_env, console_script

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

TIMEOUT_S = 400


def _installed(*modules: str) -> bool:
    try:
        return all(importlib.util.find_spec(m) is not None for m in modules)
    except ModuleNotFoundError:  # a missing parent package
        return False


HAS_SUBMITIT = _installed("submitit", "hydra_plugins.hydra_submitit_launcher")
HAS_RAY = _installed("ray", "hydra_plugins.hydra_ray_launcher")
NEEDS = {
    "submitit": (HAS_SUBMITIT, 'the [submit] extra is not installed (pip install -e ".[submit]")'),
    "ray": (HAS_RAY, 'the [ray] extra is not installed (pip install -e ".[ray]")'),
}
COMMANDS = {
    "submitit": ["-m", "hydra/launcher=submitit_local", "experiment=smoke", "seed=0"],
    "ray": [
        "-m",
        "hydra/launcher=ray",
        "+hydra.launcher.ray.init.num_cpus=1",
        "+hydra.launcher.ray.init.include_dashboard=false",
        "experiment=smoke",
        "seed=0",
    ],
}
TEST_OF = {
    "submitit": "test_submitit_local_launcher_writes_the_run_directory",
    "ray": "test_ray_launcher_on_a_local_instance",
}


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory, request):
    root = tmp_path_factory.mktemp("launchers")
    selected = {
        item.originalname
        for item in request.session.items
        if getattr(item, "module", None) is request.module
    }
    env = cli_env(RAY_USAGE_STATS_ENABLED="0")
    procs = {}
    for name, args in COMMANDS.items():
        if not NEEDS[name][0] or TEST_OF[name] not in selected:
            continue
        cwd = root / name
        cwd.mkdir()
        argv = [console_script("stages-train"), *args, f"hydra.sweep.dir={cwd / 'sweep'}"]
        with (cwd / "out.txt").open("w") as out, (cwd / "err.txt").open("w") as err:
            procs[name] = subprocess.Popen(
                argv, cwd=cwd, env=env, stdout=out, stderr=err, stdin=subprocess.DEVNULL
            )

    def result(name: str) -> tuple[int, str, Path]:
        code = procs[name].wait(timeout=TIMEOUT_S)
        cwd = root / name
        return code, (cwd / "out.txt").read_text() + (cwd / "err.txt").read_text(), cwd

    yield result
    for proc in procs.values():
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _need(name: str) -> None:
    ok, reason = NEEDS[name]
    if not ok:
        pytest.skip(reason)


def _summary_rows(sweep: Path) -> list[dict[str, str]]:
    with (sweep / "summary.csv").open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_submitit_local_launcher_writes_the_run_directory(sweeps):
    _need("submitit")
    code, output, cwd = sweeps("submitit")
    assert code == 0, output[-4000:]
    job = cwd / "sweep" / "0"
    result = json.loads((job / "eval.json").read_text())
    assert result["task"] == "gridworld" and len(result["training"]["stages"]) == 5
    assert all((job / f"stage_{k}.pt").is_file() for k in range(5))
    assert (job / ".hydra" / "overrides.yaml").is_file() and (job / "metrics.csv").is_file()
    assert [r["status"] for r in _summary_rows(cwd / "sweep")] == ["done"]


def test_ray_launcher_on_a_local_instance(sweeps):
    _need("ray")
    code, output, cwd = sweeps("ray")
    assert code == 0, output[-4000:]
    assert "Started a local Ray instance" in output
    job = cwd / "sweep" / "0"
    assert json.loads((job / "eval.json").read_text())["task"] == "gridworld"
    assert all((job / f"stage_{k}.pt").is_file() for k in range(5))
    assert [r["status"] for r in _summary_rows(cwd / "sweep")] == ["done"]
