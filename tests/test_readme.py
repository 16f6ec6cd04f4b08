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
