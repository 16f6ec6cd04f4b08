"""The README's Python examples run as written."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(marker: str) -> list[str]:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    return [b for b in blocks if marker in b]


def test_drop_in_example_runs(capsys: pytest.CaptureFixture[str]) -> None:
    (code,) = _blocks("StageTransform(upper_half")
    exec(compile(code, str(README), "exec"), {})
    first, second = capsys.readouterr().out.splitlines()[:2]
    steps, transition, terminated = first.split()
    assert transition == "True" and terminated == "True"  # the episode ended at the transition
    rewritten, raw = (float(v) for v in second.split())
    assert rewritten > raw  # r + 0.99 * V_1(s_{t+1}) with V_1 > 0 in the upper half


def test_drop_in_training_loop_runs(capsys: pytest.CaptureFixture[str]) -> None:
    (code,) = _blocks("def train_stage(k, next_value")
    exec(compile(code, str(README), "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.strip().splitlines()[-1]
    reached, _, total, *_ = out.split()
    assert out.endswith("whole-task episodes reached the target")
    assert int(total) == 8 and 0 <= int(reached) <= 8


def test_readme_commands_use_shipped_groups() -> None:
    """Every `group=option` of the README's stages-train commands names a shipped config."""
    conf = README.parent / "conf"
    text = README.read_text()
    yours = {"line"}  # the README's example of a task in a config dir of one's own
    for group in ("task", "schedule", "logger", "experiment"):
        for option in set(re.findall(rf"(?<![./\w]){group}=(\w+)", text)) - yours:
            assert (conf / group / f"{option}.yaml").is_file(), f"{group}={option}"
