"""scripts/stage_evaluations.py: a stage's evaluations read back from run directories."""

import subprocess
from pathlib import Path

import pytest
from helpers import run_script

pytestmark = [pytest.mark.e2e]

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "stage_evaluations.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return run_script(SCRIPT, *args, timeout=120)


def test_prints_each_stages_evaluations_per_run(tmp_path):
    for seed, ret in ((0, 0.25), (1, 0.5)):
        run = tmp_path / f"a_seed{seed}"
        run.mkdir()
        (run / "metrics.csv").write_text(
            "name,step,value\n"
            "train/stage_0/loss_qvalue,1024,0.3\n"
            f"eval/stage_0/discounted_return,2048,{ret}\n"
            f"eval/stage_0/discounted_return,4096,{ret * 2}\n"
            "eval/stage_0/mean_steps,4096,18.5\n"
            "eval/stage_1/discounted_return,2048,0.9\n"
            "eval/task/success_rate,4096,1.0\n"
        )
    out = _run(str(tmp_path / "a_seed0"), str(tmp_path / "a_seed1"), "--stage", "0")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "stage 0"
    header = (
        "| frames | a_seed0 mean_steps | a_seed0 discounted_return | a_seed1 mean_steps | "
        "a_seed1 discounted_return |"
    )
    assert header in lines
    assert "| 2048 |  | 0.25 |  | 0.5 |" in lines
    assert "| 4096 | 18.5 | 0.5 | 18.5 | 1 |" in lines
    assert "stage 1" not in out.stdout
    every = _run(str(tmp_path / "a_seed0"), "--metrics", "discounted_return")
    assert every.returncode == 0, every.stderr
    assert "stage 0" in every.stdout and "stage 1" in every.stdout
    assert "| 2048 | 0.9 |" in every.stdout


def test_a_missing_run_directory_is_named(tmp_path):
    out = _run(str(tmp_path / "nowhere"))
    assert out.returncode == 2
    assert "nowhere/metrics.csv does not exist" in out.stderr
