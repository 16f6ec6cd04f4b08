"""A trained run's policy outside training: load_policy on the env's own TensorDicts, and the
whole stacked policy exported with torch.export, run by a process that imports torch alone."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from helpers import TINY_STAGE, hydra_config
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_stages import Experiment, StackedPolicy, load_policy, load_run
from torchrl_stages.envs import GridWorldEnv
from torchrl_stages.runs.export import METADATA, export_policy, main
from torchrl_stages.transforms import StageTransform

pytestmark = pytest.mark.slow

STAGES = {"gridworld": ["s0", "s1"], "cargo": ["slider", "propelled"]}
TWO_STAGE_GRID = ["task.env.size=10", "task.env.num_stages=2"]
TWO_STAGE_GRID += [f"~task.stages.s{k}" for k in (2, 3, 4)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A finished tiny run of each task: the grid world (DQN, its stage from a stage
    function), cargo (TD3 then DQN, one action entry per robot; the env tracks its stage)."""
    root, found = tmp_path_factory.mktemp("runs"), {}
    with hydra_config() as compose:
        for task, stages in STAGES.items():
            tiny = [f"task.stages.{s}.{k}={v}" for s in stages for k, v in TINY_STAGE.items()]
            cfg = compose(
                f"task={task}",
                *(TWO_STAGE_GRID if task == "gridworld" else []),
                *tiny,
                "eval.episodes=4",
                "eval.plots=false",
                "logger=none",
                "progress=false",
            )
            torch.manual_seed(0)
            Experiment(cfg, root / task).run()
            found[task] = root / task
    return found


def every_stage(run_dir: Path) -> TensorDict:
    """Observations of the run's env as it gives them, from starts inside every stage."""
    task = load_run(run_dir).task
    parts = []
    for k in range(task.num_stages):
        env = task.base_env(8, start_stage=k)
        env.set_seed(k)
        parts.append(env.rollout(6, break_when_any_done=False).reshape(-1))
    return torch.cat(parts)


def test_loaded_policy_acts_on_the_env_s_own_tensordicts(runs):
    """No "stage" entry: the policy computes it with the task's stage function, and acts as
    on the env tagged by StageTransform."""
    run_dir = runs["gridworld"]
    policy, task = load_policy(run_dir), load_run(run_dir).task
    base = task.base_env(8)
    assert "stage" not in base.reset().keys()
    with torch.no_grad():
        base.set_seed(1)
        plain = base.rollout(20, policy, break_when_any_done=False)
        tagged_env = TransformedEnv(task.base_env(8), StageTransform(base.stage_fn, 2))
        tagged_env.set_seed(1)
        tagged = tagged_env.rollout(20, policy, break_when_any_done=False)
    assert torch.equal(plain["action"], tagged["action"])
    assert set(tagged["stage"].unique().tolist()) == {0, 1}  # both stages acted


EXPORTED = textwrap.dedent(
    """
    import json, sys
    import torch

    path, data, out = sys.argv[1:]
    extra = {"policy.json": ""}
    program = torch.export.load(path, extra_files=extra).module()
    meta = json.loads(extra["policy.json"])
    inputs = torch.load(data)
    names = [".".join(e["key"]) if isinstance(e["key"], list) else e["key"] for e in meta["inputs"]]
    actions = program(*(inputs[n] for n in names))
    torch.save(list(actions), out)
    print(json.dumps(sorted(m for m in sys.modules if m.startswith(("tensordict", "torchrl")))))
    """
)


def _key(entry: dict):
    """An input's or output's key, as ``policy.json`` writes it, as a TensorDict key."""
    return entry["key"] if isinstance(entry["key"], str) else tuple(entry["key"])


def _name(entry: dict) -> str:
    return entry["key"] if isinstance(entry["key"], str) else ".".join(entry["key"])


def test_a_stacked_policy_exports_with_an_example(tmp_path):
    """Without a run: the stage function is in the program, which acts on each row's stage."""
    env = GridWorldEnv(batch_size=(4,), size=10, num_stages=2)

    def move(action: int) -> TensorDictModule:  # 3: right, 1: down
        return TensorDictModule(
            lambda o: o[..., 0].long() * 0 + action, ["observation"], ["action"]
        )

    policy = StackedPolicy([move(3), move(1)], stage_fn=env.stage_fn)
    file = export_policy(policy, tmp_path / "p.pt2", env.reset())
    (actions,) = torch.export.load(file).module()(torch.tensor([[0.0, 0.0], [0.0, 1.8]]))
    assert actions.tolist() == [3, 1]  # cells (0, 0) and (0, 9): stages 0 and 1


@pytest.mark.parametrize("task", list(STAGES))
def test_exported_policy_runs_with_torch_alone(runs, task, tmp_path):
    """The .pt2 file, run by a process that imports neither tensordict, torchrl nor this
    package, gives the greedy actions of the loaded policy on observations of every stage."""
    run_dir = runs[task]
    file = export_policy(run_dir, tmp_path / "policy.pt2")
    extra = {METADATA: ""}
    torch.export.load(file, extra_files=extra)
    meta = json.loads(extra[METADATA])
    data = every_stage(run_dir)
    policy = load_policy(run_dir)
    assert torch.bincount(policy.stage(data), minlength=2).min() >= 8  # every stage
    torch.save({_name(e): data.get(_key(e)) for e in meta["inputs"]}, tmp_path / "inputs.pt")
    (tmp_path / "run_exported.py").write_text(EXPORTED)
    done = subprocess.run(
        [sys.executable, "run_exported.py", file, "inputs.pt", "actions.pt"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.splitlines()[-1]) == []  # torch alone
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = policy(data.clone())
    actions = torch.load(tmp_path / "actions.pt")
    keys = [_key(e) for e in meta["outputs"]]
    assert keys == list(dict.fromkeys(load_run(run_dir).task.specs(k).action_key for k in (0, 1)))
    for key, action in zip(keys, actions, strict=True):
        assert torch.equal(action, expected.get(key)), key


def test_stages_export_writes_the_file_and_names_its_inputs(runs, tmp_path, capsys):
    main([str(runs["gridworld"]), str(tmp_path / "grid.pt2")])
    assert capsys.readouterr().out.strip() == (
        f"Wrote {tmp_path / 'grid.pt2'}: inputs observation [batch, 2] float32; "
        "outputs action [batch] int64"
    )
    program = torch.export.load(tmp_path / "grid.pt2").module()
    (action,) = program(torch.tensor([[0.0, 0.0]]))  # one observation: a batch of 1
    assert action.shape == (1,)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["{run}", "{tmp}/policy.onnx"], r"policy\.onnx: the file must end in \.pt2\. Fix:"),
        (["{run}", "{tmp}/no/such/dir/p.pt2"], r"dir is not a directory\. Fix:"),
        (["{tmp}/nothing", "{tmp}/p.pt2"], r"nothing is not a torchrl-stages run directory"),
    ],
)
def test_stages_export_refuses_bad_input(runs, tmp_path, capsys, args, message):
    argv = [a.format(run=runs["gridworld"], tmp=tmp_path) for a in args]
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("stages-export: ")
    assert re.search(message, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written
