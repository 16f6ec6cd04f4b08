"""Fixtures of the test-suite, one intra-op thread (small nets) and a fixed seed. Shared helpers
are in ``helpers.py``."""

import functools
from collections.abc import Callable, Iterator

import pytest
import torch
from helpers import TINY_STAGE, hydra_config, run_cli
from omegaconf import DictConfig

torch.set_num_threads(1)


@pytest.fixture
def compose_cfg() -> Iterator[Callable[..., DictConfig]]:
    """``compose(*overrides)`` of the root config, for one test."""
    with hydra_config() as compose_fn:
        yield compose_fn


@pytest.fixture(scope="module")
def hydra_compose() -> Iterator[Callable[..., DictConfig]]:
    """``compose(*overrides)`` of the root config, Hydra initialised once for the module (a
    compose costs ~0.2 s) and results cached: treat the configs as read-only."""
    with hydra_config() as compose_fn:
        yield functools.cache(compose_fn)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


@pytest.fixture
def train_tiny(tmp_path):
    """``train_tiny(task, stages, *overrides)`` runs ``stages-train task=<task>`` as a
    subprocess in ``tmp_path`` with tiny budgets for the named stages; returns the completed
    process and the run directory."""

    def run(task: str, stages: list[str], *overrides: str):
        tiny = [f"task.stages.{s}.{k}={v}" for s in stages for k, v in TINY_STAGE.items()]
        run_dir = tmp_path / "run"
        argv = ["stages-train", f"task={task}", f"hydra.run.dir={run_dir}", *tiny, *overrides]
        return run_cli(argv, tmp_path), run_dir

    return run


def pytest_collection_modifyitems(config, items):
    """With ``pytest -n N --dist loadgroup`` (pytest-xdist, what CI runs): the tests of one
    module run on one worker, so a module-scoped fixture (a trained run several tests read) is
    built once; the documentation pages, the longest tests and independent of each other, are
    spread over the workers."""
    if not config.pluginmanager.hasplugin("xdist"):
        return
    for item in items:
        if item.path.name != "test_docs.py":
            item.add_marker(pytest.mark.xdist_group(item.path.stem))
