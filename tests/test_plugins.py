"""Algorithms are plug-ins: one module each, known through one registry, and a learner class of
your own trains a stage with no change to the package."""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from helpers import TINY_STAGE, docstring_ids, hydra_config, tiny_grid
from my_learner import TinyQLearner
from torchrl.objectives import DQNLoss, SoftUpdate

import torchrl_stages
from torchrl_stages.config import ConfigError
from torchrl_stages.failures import DivergenceError
from torchrl_stages.learners import ALGORITHMS, learner_class, make_learner, register_algorithm
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.loss_value import value_from_loss
from torchrl_stages.runs.experiment import Experiment, build_task
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.loading import load_run

PACKAGE = Path(torchrl_stages.__file__).parent
TWO_STAGES = tiny_grid()


def compose(*overrides: str):
    with hydra_config() as compose_fn:
        return compose_fn(*TWO_STAGES, *overrides)


# ---------------------------------------------------------------------- one module each
def _names(source: str) -> list[str]:
    """The identifiers and string constants of a module's code (docstrings left out)."""
    tree = ast.parse(source)
    docstrings = docstring_ids(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            out.append(node.id)
        elif isinstance(node, ast.Attribute):
            out.append(node.attr)
        elif isinstance(node, ast.alias):
            out.extend([node.name, node.asname or ""])
        elif isinstance(node, ast.FunctionDef | ast.ClassDef):
            out.append(node.name)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if id(node) not in docstrings:
                out.append(node.value)
    return out


def _words(text: str) -> str:
    """``text`` with camel case split by underscores, lower case (``DQNLearner`` ->
    ``dqn_learner``)."""
    text = re.sub(r"([A-Z]+)([A-Z][a-z])", r"\1_\2", text)
    return re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", text).lower()


def _pattern(name: str) -> re.Pattern:
    return re.compile(rf"(?<![a-z0-9]){re.escape(name)}(?![a-z0-9])")


def test_no_module_outside_an_algorithms_own_file_names_it():
    files = [*PACKAGE.rglob("*.py")]
    found = []
    for name in ALGORITHMS:
        own = PACKAGE / "learners" / f"{name}.py"
        assert own.is_file(), f"algorithm {name} is not one module of torchrl_stages/learners/"
        for path in files:
            if path == own:
                continue
            # an algorithm's file may name itself (discrete_sac.py says "discrete_sac")
            itself = _pattern(path.stem) if path.stem in ALGORITHMS else None
            for text in _names(path.read_text()):
                words = itself.sub(" ", _words(text)) if itself else _words(text)
                if _pattern(name).search(words):
                    found.append(f"{path.relative_to(PACKAGE.parent)}: {text!r} names {name}")
    assert not found, "\n".join(found)


def test_the_checker_sees_a_name_in_code():
    names = [_words(t) for t in _names('"""DQN in a docstring"""\nx = DQNLearner\ny = "td3"\n')]
    assert "dqn_learner" in names and "td3" in names and "dqn in a docstring" not in names


@dataclass
class EchoConfig(DQNConfig):
    algo: str = "echo"


class EchoLearner(DQNLearner):
    """A registered algorithm defined outside the package: DQN under another name."""

    algo, Config = "echo", EchoConfig


@pytest.fixture
def echo():
    register_algorithm(EchoLearner)
    try:
        yield EchoLearner
    finally:
        ALGORITHMS.pop("echo")


def test_a_registered_algorithm_is_known_to_the_store_validation_and_help(echo):
    cfg = compose(
        "algo@task.stages.s0=echo_schema",
        *[f"task.stages.s0.{k}={v}" for k, v in TINY_STAGE.items()],
    )
    assert cfg.task.stages.s0.algo == "echo"
    task = build_task(cfg)  # validation: its own checks, its action spaces
    assert type(make_learner(task.stage_cfg(0), task.specs(0))) is EchoLearner
    with pytest.raises(ConfigError, match=r"task\.stages\.s0\.eps_init=2\.0"):
        build_task(compose("algo@task.stages.s0=echo_schema", "task.stages.s0.eps_init=2.0"))
    from omegaconf import OmegaConf

    assert "echo" in OmegaConf.create({"x": "${stages_algorithms:}"}).x.split("|")


def test_a_diverged_stage_names_its_algorithms_learning_rates():
    learner = learner_class({"algo": "td3"})
    error = DivergenceError(0, "s0", learner.__new__(learner), FloatingPointError("nan"))
    assert "task.stages.s0.lr or task.stages.s0.actor_lr" in str(error)


def test_target_value_dispatches_through_the_registry():
    from torchrl.data import Categorical
    from torchrl.modules import MLP, QValueActor

    qnet = QValueActor(MLP(in_features=2, out_features=3, num_cells=[8]), spec=Categorical(3))
    loss = DQNLoss(qnet, action_space="categorical", delay_value=True)
    SoftUpdate(loss, tau=0.1)  # a loss with targets has its updater
    assert type(value_from_loss(loss)).__name__ == "QMaxValue"
    with pytest.raises(TypeError, match="value_from_loss supports"):
        value_from_loss(torch.nn.Linear(1, 1))


# ---------------------------------------------------------------------- your own learner
def test_your_own_learner_trains_a_stage_and_loads_with_trust(tmp_path, monkeypatch):
    own = ["+task.stages.s0.learner._target_=my_learner.TinyQLearner"]
    cfg = compose(*own, "+task.stages.s0.learner.hidden=16", "task.stages.s0.frames=512")
    [result] = Experiment(cfg, tmp_path / "run").run()
    assert result["training"]["stages"][0]["frames"] == 512
    assert result["training"]["stages"][0]["updates"] > 0
    with pytest.raises(RunDirError, match=r"task\.stages\.s0\.learner\._target_"):
        load_run(tmp_path / "run")  # a run directory names code: untrusted
    run = load_run(tmp_path / "run", trust=True)
    assert type(run.learners[0]) is TinyQLearner and run.learners[0].q[0].out_features == 16
    assert type(run.learners[1]) is DQNLearner
    # where the learner's module is not importable, loading names it and the fix
    tests_dir = str(Path(__file__).parent)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != tests_dir])
    monkeypatch.delitem(sys.modules, "my_learner")
    with pytest.raises(RunDirError, match=r"config\.yaml: .*module `my_learner` is not importable"):
        load_run(tmp_path / "run", trust=True)


def test_a_learner_that_cannot_be_imported_names_the_cause():
    with pytest.raises(
        ConfigError,
        match=r"task\.stages\.s0\.learner\._target_=no_pkg\.X: module `no_pkg` is not "
        r"importable\. Fix: add its directory to PYTHONPATH or pip install it",
    ):
        build_task(compose("+task.stages.s0.learner._target_=no_pkg.X"))
    with pytest.raises(ConfigError, match=r"module `my_learner` has no `TinyQ`\. Fix: check"):
        build_task(compose("+task.stages.s0.learner._target_=my_learner.TinyQ"))
    with pytest.raises(ConfigError, match="is not a subclass of torchrl_stages.learners.Learner"):
        build_task(compose("+task.stages.s0.learner._target_=torch.nn.Linear"))


# ---------------------------------------------------------------------- the two SACs
@pytest.mark.slow
def test_sac_and_discrete_sac_train_cargos_stages_from_one_override_each(tmp_path):
    with hydra_config() as compose_fn:
        cfg = compose_fn(
            "task=cargo",
            "experiment=smoke",
            "algo@task.stages.slider=sac",
            "algo@task.stages.propelled=discrete_sac",
            "eval.plots=false",
            "progress=false",
        )
    [result] = Experiment(cfg, tmp_path / "run").run()
    assert [s["updates"] > 0 for s in result["training"]["stages"]] == [True, True]
    run = load_run(tmp_path / "run")
    assert [learner.algo for learner in run.learners] == ["sac", "discrete_sac"]


def test_an_algorithm_in_the_wrong_action_space_names_the_ones_that_fit():
    with pytest.raises(ConfigError, match=r"sac needs a continuous action space.*discrete_sac"):
        build_task(compose("algo@task.stages.s0=sac"))
    with pytest.raises(ConfigError, match=r"task\.stages\.s0\.alpha_lr=0\.0: must be > 0"):
        build_task(compose("algo@task.stages.s0=discrete_sac", "task.stages.s0.alpha_lr=0"))
