"""Schedules and tasks are registered, not listed: no module outside a schedule's own file
compares its name, no module of the library names a task, the help lists what the registries
hold, and a task or schedule of your own is picked up."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from helpers import docstring_ids, hydra_config, tiny_grid

import torchrl_stages
import torchrl_stages.envs  # noqa: F401  (registers the shipped tasks)
from torchrl_stages.config import ConfigError
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.schedules import SCHEDULES, BackwardSchedule, get_schedule, register_schedule
from torchrl_stages.task_registry import TASKS, register_task, task_report

PACKAGE = Path(torchrl_stages.__file__).parent


def string_constants(path: Path) -> set[str]:
    """The string constants of a module's code, docstrings left out."""
    tree = ast.parse(path.read_text())
    docstrings = docstring_ids(tree)
    return {
        node.value
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in docstrings
    }


def test_no_module_outside_a_schedules_own_file_names_it():
    found = []
    for name in SCHEDULES:
        own = PACKAGE / "schedules" / f"{name}.py"
        assert own.is_file(), f"schedule {name} is not one module of torchrl_stages/schedules/"
        for path in PACKAGE.rglob("*.py"):
            # config/schema.py: the default selection (conf/config.yaml picks it too)
            allowed = path == own or (path.name == "schema.py" and name == "backward")
            if not allowed and name in string_constants(path):
                found.append(f"{path.relative_to(PACKAGE.parent)} names {name!r}")
    assert not found, "\n".join(found)


def test_no_module_of_the_library_names_a_task():
    assert set(TASKS) >= {"gridworld", "manipulator", "cargo"}
    found = [
        f"{path.relative_to(PACKAGE.parent)} names {name!r}"
        for path in PACKAGE.rglob("*.py")
        for name in TASKS
        if name in string_constants(path)
    ]
    assert not found, "\n".join(found)


def test_unknown_schedule_names_the_known_ones():
    with pytest.raises(ConfigError, match=r"schedule\.name='mine'.*known: backward, flat, joint"):
        get_schedule("mine")


def test_a_schedule_of_your_own_trains_through_the_registry(tmp_path):
    calls = []

    @register_schedule
    class Counting(BackwardSchedule):
        name = "counting"

        def run(self, task, group):
            calls.append(task.num_stages)
            return super().run(task, group)

    try:
        with hydra_config() as compose:
            cfg = compose(*tiny_grid(), "schedule.name=counting")
        [result] = Experiment(cfg, tmp_path / "run").run()
    finally:
        SCHEDULES.pop("counting")
    assert calls == [2] and result["training"]["schedule"] == "counting"


def test_a_task_report_of_your_own_reaches_eval_json(tmp_path):
    def report(task, learners, evaluation, run_dir, plots):
        return {"stages": task.num_stages, "note": "mine"}

    register_task("grid_mine", report=report, headline=["stages"])
    try:
        with hydra_config() as compose:
            cfg = compose(*tiny_grid(), "task.name=grid_mine")
        [result] = Experiment(cfg, tmp_path / "run").run()
    finally:
        TASKS.pop("grid_mine")
    assert result["task_metrics"] == {"stages": 2, "note": "mine"}
    assert result["headline_metrics"] == ["stages"]
    assert task_report("no_such_task") is None
