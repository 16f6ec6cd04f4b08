"""scripts/profile_stage.py and scripts/profile_update.py on a tiny two-stage grid world: each
writes the rows and the table it prints, and refuses Hydra overrides placed after its lists."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
TINY_GRID = [
    "task.env.size=10",
    "task.env.num_stages=2",
    *[f"~task.stages.s{k}" for k in (2, 3, 4)],
    *[
        f"task.stages.s{k}.{key}={value}"
        for k in (0, 1)
        for key, value in {
            "frames": 1024,
            "frames_per_batch": 128,
            "num_envs": 16,
            "init_random_frames": 128,
            "batch_size": 32,
            "updates_per_batch": 2,
            "eval_every": 512,
            "eval_episodes": 8,
            "min_frames": 0,
        }.items()
    ],
]


def run_script(name: str, *args: str, env: dict[str, str] | None = None):
    return subprocess.run(
        [sys.executable, str(SCRIPTS / name), *args],
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
        env=None if env is None else {**os.environ, **env},
    )


@pytest.mark.e2e
def test_profile_update_times_each_stage(tmp_path):
    done = run_script(
        "profile_update.py",
        *TINY_GRID,
        "--stages",
        "gridworld:0",
        "gridworld:1",
        "--compile",
        "off",
        "--updates",
        "5",
        "--warmup",
        "1",
        "--out",
        str(tmp_path),
        env={"TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "inductor")},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [(r["stage"], r["algo"], r["compile"]) for r in rows] == [
        (0, "dqn", "off"),
        (1, "dqn", "off"),
    ]
    for row in rows:
        assert row["batch_size"] == 32 and row["device"] == "cpu"
        assert row["ms_per_update"] > 0 and row["first_call_s"] > 0
    table = (tmp_path / "table.md").read_text()
    # the command as run: an inductor cache directory changes what a first call costs
    assert f"$ TORCHINDUCTOR_CACHE_DIR={tmp_path / 'inductor'} python " in table
    assert "profile_update.py" in table and "machine speed" in table
    assert table.count("| gridworld |") == 2


@pytest.mark.e2e
def test_profile_stage_breaks_a_run_into_phases(tmp_path):
    done = run_script("profile_stage.py", *TINY_GRID, "--task", "gridworld", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr[-3000:]
    (run,) = json.loads((tmp_path / "rows.json").read_text())
    assert [r["stage"] for r in run["stages"]] == [0, 1]
    for row in run["stages"]:
        assert row["updates"] > 0 and row["update"] > 0 and row["collect"] > 0
        assert row["updates_per_s"] > 0 and row["frames_per_s"] > 0
    assert run["task_metrics"]["optimal_steps_from_origin"] == 18  # the 10 x 10 grid's shortest
    assert "optimal_steps_from_origin=18" in done.stdout
    assert "optimal_steps_from_origin=18" in (tmp_path / "table.md").read_text()
    assert (tmp_path / "table.md").read_text().count("| 1 | off |") == 2


def main_of(script: str, monkeypatch):
    """The ``main`` of a script in ``scripts/``, imported in this process (argument errors exit
    before anything runs, so the refusals need no subprocess)."""
    monkeypatch.syspath_prepend(str(SCRIPTS))
    module = importlib.import_module(script.removesuffix(".py"))
    return module.main


@pytest.mark.parametrize("script", ["profile_stage.py", "profile_update.py"])
def test_an_override_after_the_compile_list_is_refused(script, monkeypatch, capsys):
    main = main_of(script, monkeypatch)
    monkeypatch.setattr(sys, "argv", [script, "--compile", "off", "device=cpu"])
    with pytest.raises(SystemExit) as raised:
        main()
    assert raised.value.code == 2
    err = capsys.readouterr().err
    assert "device=cpu" in err and "before" in err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--compile", "fast"], "not compile modes"),
        (["compile=default"], "--compile, not a compile= override"),
        (["--stages", "gridworld"], "each is TASK:STAGE"),
    ],
)
def test_profile_update_refuses_bad_arguments(args, message, monkeypatch, capsys):
    main = main_of("profile_update.py", monkeypatch)
    monkeypatch.setattr(sys, "argv", ["profile_update.py", *args])
    with pytest.raises(SystemExit) as raised:
        main()
    assert raised.value.code == 2 and message in capsys.readouterr().err
