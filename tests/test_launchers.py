"""Sweeps beyond the basic launcher, through the optional extras: Optuna with persistent SQLite
storage (``[optuna]``), submitit's local launcher (``[submit]``, the SLURM launcher's local
twin) and Ray (``[ray]``, a local Ray instance that the launcher's ``ray.init`` starts inside
``stages-train`` and that stops when it exits). Each test is skipped, with the reason, only when
its extra is not installed (``pip install -e ".[optuna,submit,ray]"``); CI installs ``[test]``
only.

Every sweep is ``experiment=smoke``; the commands start together when the module's first test
runs and each test waits for its own.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import warnings
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


def _sqlalchemy_below_2() -> bool:
    if not _installed("sqlalchemy"):
        return False
    from importlib.metadata import version

    return int(version("sqlalchemy").split(".")[0]) < 2


HAS_OPTUNA = _installed("optuna", "hydra_plugins.hydra_optuna_sweeper") and _sqlalchemy_below_2()
HAS_SUBMITIT = _installed("submitit", "hydra_plugins.hydra_submitit_launcher")
HAS_RAY = _installed("ray", "hydra_plugins.hydra_ray_launcher")
NEEDS = {
    "optuna": (HAS_OPTUNA, 'the [optuna] extra is not installed (pip install -e ".[optuna]")'),
    "optuna_direction": (HAS_OPTUNA, "the [optuna] extra is not installed"),
    "submitit": (HAS_SUBMITIT, 'the [submit] extra is not installed (pip install -e ".[submit]")'),
    "ray": (HAS_RAY, 'the [ray] extra is not installed (pip install -e ".[ray]")'),
}
OPTUNA = [
    "-m",
    "hydra/sweeper=optuna",
    "hydra.sweeper.storage=sqlite:///study.db",
    "hydra.sweeper.study_name=smoke_steps",
    "hydra.sweeper.n_trials=2",
    "hydra.sweeper.n_jobs=1",
    "hydra.sweeper.sampler.seed=0",
    "task.stages.s3.lr=tag(log,interval(1e-4,1e-2))",
    "experiment=smoke",
    "eval.plots=false",
]
COMMANDS = {
    # the objective: fewest whole-task steps, minimized by the sweeper too
    "optuna": [
        *OPTUNA,
        "objective.metric=mean_steps",
        "objective.direction=minimize",
        "hydra.sweeper.direction=minimize",
    ],
    # Optuna's own default direction (minimize) against the default objective (maximize)
    "optuna_direction": OPTUNA,
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
    "optuna": "test_optuna_sqlite_study_completes_and_reloads",
    "optuna_direction": "test_optuna_direction_must_match_the_objective",
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


def test_optuna_sqlite_study_completes_and_reloads(sweeps):
    _need("optuna")
    code, output, cwd = sweeps("optuna")
    assert code == 0, output[-4000:]
    assert (cwd / "study.db").is_file()
    with warnings.catch_warnings():  # optuna 2.x and SQLAlchemy 1.4 deprecation notices
        warnings.simplefilter("ignore")
        import optuna

        study = optuna.load_study(study_name="smoke_steps", storage=f"sqlite:///{cwd / 'study.db'}")
        trials = study.get_trials(deepcopy=False)
        direction = study.direction
    assert direction == optuna.study.StudyDirection.MINIMIZE
    assert len(trials) == 2 and all(t.state.name == "COMPLETE" for t in trials)
    # each trial's value is its run's objective: eval.json's mean_steps
    steps = {
        json.loads((cwd / "sweep" / str(k) / "eval.json").read_text())["mean_steps"]
        for k in range(2)
    }
    assert {t.value for t in trials} == steps
    assert all(1e-4 <= t.params["task.stages.s3.lr"] <= 1e-2 for t in trials)
    rows = _summary_rows(cwd / "sweep")  # the sweep summary works with any sweeper
    assert [r["status"] for r in rows] == ["done", "done"]


def test_optuna_direction_must_match_the_objective(sweeps):
    _need("optuna_direction")
    code, output, cwd = sweeps("optuna_direction")
    assert code == 2, output[-4000:]
    assert "hydra.sweeper.direction='minimize'" in output
    assert "Fix: add hydra.sweeper.direction=maximize" in output
    assert not (cwd / "sweep" / "0").exists()  # refused before any job ran


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
