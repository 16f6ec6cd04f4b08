"""scripts/benchmark_stage.py on a tiny two-stage grid world: a row is the stage of a whole run
with the same seed, and bad arguments fail before anything trains."""

from __future__ import annotations

import json
import sys

import pytest
from test_profile_scripts import SCRIPTS, TINY_GRID, main_of, run_script

from torchrl_stages.config import register_configs
from torchrl_stages.learners import ALGORITHMS

SCRIPTS_ARGS = ["--task", "gridworld", *TINY_GRID]


@pytest.mark.slow
def test_a_stage_alone_is_the_stage_of_a_whole_run(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPTS))
    from _benchmark import train

    register_configs(ALGORITHMS)
    whole = train("gridworld", tmp_path / "run", "seed=4", *TINY_GRID)["training"]["stages"]
    out = tmp_path / "alone"
    done = run_script(
        "benchmark_stage.py",
        *SCRIPTS_ARGS,
        "--stage",
        "0",
        "--next-run",
        str(tmp_path / "run"),
        "--seeds",
        "4",
        "--variant",
        "base:",
        "--variant",
        "fast: task.stages.s0.lr=1e-2 task.stages.s0.tau=0.5",
        "--out",
        str(out),
    )
    assert done.returncode == 0, done.stderr[-3000:]
    base, fast = json.loads((out / "rows.json").read_text())
    assert (base["variant"], base["seed"], base["stage"]) == ("base", 4, 0)
    keys = (
        "frames",
        "updates",
        "success_rate",
        "value_error",
        "discounted_return",
        "early_stopped",
    )
    for key in keys:
        assert base[key] == whole[0][key], key
    assert base["discounted_return"] is not None
    assert fast["variant"] == "fast" and fast["value_error"] != base["value_error"]
    table = (out / "table.md").read_text()
    assert table.count("| base | 4 |") == 1 and table.count("| fast | 4 |") == 1
    assert "- fast (task.stages.s0.lr=1e-2 task.stages.s0.tau=0.5): frames median" in table
    assert "- base (no override)" in table and "machine speed" in table
    assert f"return median {base['discounted_return']:.4f}" in table


@pytest.mark.parametrize(
    "args, message",
    [
        (["--stage", "0"], "needs the value of stage 1: pass --next-run"),
        (["--stage", "1", "--next-run", "somewhere"], "is the last of 2; drop --next-run"),
        (["--stage", "2"], "--stage 2 is outside 0..1"),
    ],
)
def test_benchmark_stage_refuses_a_stage_without_its_next_value(
    args, message, tmp_path, monkeypatch, capsys
):
    main = main_of("benchmark_stage.py", monkeypatch)
    monkeypatch.setattr(
        sys, "argv", ["benchmark_stage.py", *args, "--out", str(tmp_path), *SCRIPTS_ARGS]
    )
    with pytest.raises(SystemExit) as raised:
        main()
    assert message in str(raised.value.code)
    assert not (tmp_path / "rows.json").exists()


@pytest.mark.parametrize("variant", ["nocolon", ":task.stages.s0.lr=1"])
def test_benchmark_stage_refuses_a_variant_without_a_name(variant, monkeypatch, capsys):
    main = main_of("benchmark_stage.py", monkeypatch)
    monkeypatch.setattr(sys, "argv", ["benchmark_stage.py", "--stage", "1", "--variant", variant])
    with pytest.raises(SystemExit) as raised:
        main()
    assert raised.value.code == 2 and "expected NAME:OVERRIDE" in capsys.readouterr().err
