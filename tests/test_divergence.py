"""The divergence guard: a non-finite value or loss stops the run, saves nothing, exits 3."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers import hydra_config, run_cli
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModule
from torchrl.data import Categorical
from torchrl.envs import TransformedEnv

from torchrl_stages.envs import GridWorldEnv
from torchrl_stages.failures import DivergenceError
from torchrl_stages.learners import StageSpecs
from torchrl_stages.learners.base import NonFiniteError
from torchrl_stages.learners.dqn import DQNConfig, DQNLearner
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.transforms import NonFiniteValueError, StageTransform

RIGHT = 3
TINY = {
    "frames": 512,
    "frames_per_batch": 128,
    "num_envs": 16,
    "init_random_frames": 128,
    "batch_size": 32,
    "updates_per_batch": 2,
    "eval_every": 0,
    "eval_episodes": 4,
    "min_frames": 0,
}
OVERRIDES = [
    "task.env.size=10",
    "task.env.num_stages=2",
    *[f"~task.stages.s{k}" for k in (2, 3, 4)],
    *[f"task.stages.s{k}.{key}={value}" for k in (0, 1) for key, value in TINY.items()],
    "task.stages.s1.lr=1e30",
    "eval.plots=false",
]


def _nan_value() -> TensorDictModule:
    return TensorDictModule(
        lambda obs: torch.full_like(obs[..., :1], float("nan")), ["observation"], ["state_value"]
    )


@pytest.mark.parametrize("start_col", [3, 4])
def test_nan_next_value_raises_on_the_transition(start_col):
    base = GridWorldEnv((1,), size=10, num_stages=2, start_cell=(0, start_col))
    env = TransformedEnv(
        base, StageTransform(base.stage_fn, 2, train_stage=0, next_value=_nan_value(), gamma=0.9)
    )
    td = env.reset()
    for _ in range(4 - start_col):  # steps inside stage 0 never ask for the next value
        td["action"] = torch.full((1,), RIGHT)
        td = env.step(td)
        assert not td["next", "stage_transition"].any()
        td = td["next"]
    td["action"] = torch.full((1,), RIGHT)  # (0, 4) -> (0, 5): into stage 1
    with pytest.raises(NonFiniteValueError, match="not finite"):
        env.step(td)


def _compose(*overrides: str):
    with hydra_config("task=gridworld") as compose_fn:
        return compose_fn(*overrides)


def _check_message(message: str) -> None:
    assert "stage 1" in message
    assert "dqn" in message
    assert "not finite" in message
    assert "task.stages.s1.lr" in message


def _all_finite(run_dir: Path) -> list[Path]:
    """The ``.pt`` files under ``run_dir``; asserts every tensor in them is finite."""
    files = sorted(run_dir.rglob("*.pt"))
    for path in files:
        stack = [torch.load(path, weights_only=False)]
        while stack:
            item = stack.pop()
            if isinstance(item, dict):
                stack.extend(item.values())
            elif isinstance(item, list | tuple):
                stack.extend(item)
            elif isinstance(item, torch.Tensor) and item.is_floating_point():
                assert torch.isfinite(item).all(), path
    return files


def test_experiment_raises_divergence_error_and_saves_nothing(tmp_path):
    cfg = _compose(*OVERRIDES)
    run_dir = tmp_path / "run"
    with pytest.raises(DivergenceError) as info:
        Experiment(cfg, run_dir).run()
    _check_message(str(info.value))
    assert info.value.stage == 1
    assert not list(run_dir.glob("stage_*.pt"))
    assert _all_finite(run_dir) == []


@pytest.mark.e2e
@pytest.mark.slow
def test_cli_exits_3_with_the_message(tmp_path):
    run_dir = tmp_path / "run"
    result = run_cli(["stages-train", *OVERRIDES, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 3, result.stderr[-2000:]
    assert "diverged" in result.stderr
    _check_message(result.stderr)
    assert not list(run_dir.glob("stage_*.pt"))
    assert _all_finite(run_dir) == []


@pytest.mark.parametrize("where", ["online", "target"])
def test_check_finite_names_the_tensor(where):
    learner = DQNLearner(
        OmegaConf.structured(DQNConfig()), StageSpecs(["observation"], 2, "action", Categorical(4))
    )
    learner.check_finite()  # a fresh learner is finite
    params = (
        learner.loss.value_network_params
        if where == "online"
        else learner.loss.target_value_network_params
    )
    tensor = next(iter(params.values(True, True)))
    with torch.no_grad():
        tensor.view(-1)[-1] = float("inf" if where == "online" else "nan")
    with pytest.raises(NonFiniteError, match="is not finite") as info:
        learner.check_finite()
    assert ("target" in info.value.what) == (where == "target")
