"""End-to-end tests of the console scripts ``stages-train`` and ``stages-eval``.

Every command runs as the console script would, in a temporary directory, with
``hydra.run.dir`` / ``hydra.sweep.dir`` pointing there and tiny per-stage budgets (in a fork of a
process that has imported the package, ``helpers.Launched``). The commands that do not depend
on each other all start together (when the module's first test runs) and each test only waits
for the ones it reads; the finished training run is shared by the tests that inspect it.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from helpers import Launched, assert_figure, console_script

from torchrl_stages import StackedPolicy, StagedTask, cli, load_policy, load_run
from torchrl_stages.cli import evaluate as stages_eval_main
from torchrl_stages.envs.gridworld.report import greedy_path

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

NUM_STAGES = 5
FRAMES = 256
EVAL_EPISODES = 8
TIMEOUT_S = 300
MAX_STEPS = 30  # episode cap (the grid world's default is 200): evaluations stay cheap
HETERO = [0.9, 0.9, 0.9, 0.99, 0.9]
HOMO = [0.99] * NUM_STAGES
PROBED = ("success_rate", "seconds", "path_optimal", "value_error")  # the grid world's probe


def tiny_overrides(
    frames: int = FRAMES,
    init_random_frames: int = 128,
    eval_every: int = 256,
    episodes: int = EVAL_EPISODES,
) -> list[str]:
    """Budgets that train each grid-world stage s0..s4 in well under a second, short episodes."""
    per_stage = {
        "frames": frames,
        "frames_per_batch": 128,
        "num_envs": 16,
        "init_random_frames": init_random_frames,
        "batch_size": 64,
        "updates_per_batch": 1,
        "eval_every": eval_every,
        "eval_episodes": episodes,
    }
    overrides = [
        f"task.stages.s{k}.{key}={value}"
        for k in range(NUM_STAGES)
        for key, value in per_stage.items()
    ]
    return [*overrides, f"eval.episodes={episodes}", f"task.env.max_steps={MAX_STEPS}"]


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str

    @property
    def output(self) -> str:
        return self.stdout + self.stderr


class Commands:
    """The module's CLI commands, by name, started at most once each."""

    def __init__(self, root: Path, used: set[str]) -> None:
        self.root = root
        self.used = used  # fixtures of the selected tests
        self.launched: dict[str, Launched] = {}

    def argv(self, name: str) -> list[str]:
        train, root = console_script("stages-train"), self.root
        if name == "smoke":
            # eval.probe: stage 0's evaluations follow the whole task (eval/task/...)
            return [train, *tiny_overrides(), "eval.probe=true", f"hydra.run.dir={root / 'run'}"]
        if name == "multirun":
            return [
                train,
                "-m",
                *tiny_overrides(frames=128, init_random_frames=0, eval_every=0, episodes=4),
                "eval.plots=false",
                "seed=0,1",
                "task/gammas=homo,hetero",
                f"hydra.sweep.dir={root / 'multi'}",
            ]
        if name == "reeval":
            directory = root / "reeval"
            shutil.copytree(root / "run", directory)
            for png in directory.glob("*.png"):
                png.unlink()
            return [console_script("stages-eval"), directory, "--no-plots"]
        if name.startswith("bad:"):
            override, _ = BAD_OVERRIDES[name.removeprefix("bad:")]
            run_dir = root / "bad" / name.removeprefix("bad:")
            return [train, *tiny_overrides(), override, f"hydra.run.dir={run_dir}"]
        if name.startswith("refused:"):  # an invalid config into the directory it names
            run_dir = root / REFUSED_DIRS[name.removeprefix("refused:")]
            if run_dir.name == "existing":  # one of the user's
                run_dir.mkdir()
                (run_dir / "notes.txt").write_text("mine\n")
            return [train, "task.stages.s0.gamma=1.5", f"hydra.run.dir={run_dir}"]
        if name.startswith("cfg:"):
            return [train, *SHOW_CFG[name.removeprefix("cfg:")], "--cfg", "job"]
        raise KeyError(name)

    def start(self, name: str) -> Launched:
        if name not in self.launched:
            tests = str(Path(__file__).resolve().parent)  # line_env, the gymnasium env
            self.launched[name] = Launched(self.argv(name), self.root, TIMEOUT_S, PYTHONPATH=tests)
        return self.launched[name]

    def result(self, name: str) -> Result:
        done = self.start(name).result()
        return Result(done.returncode, done.stdout, done.stderr)

    def stop_all(self) -> None:
        for launched in self.launched.values():
            launched.stop()


# name -> (override, what stderr must name)
BAD_OVERRIDES = {
    "gamma": ("task.stages.s0.gamma=1.5", "task.stages.s0.gamma"),
    "algo": ("algo@task.stages.s1=td3", "task.stages.s1.algo"),
    "unknown_key": ("task.stages.s0.lrr=1", "Fix: did you mean task.stages.s0.lr?"),
    "added_unknown_key": ("+task.stages.s0.lrr=1", "Fix: did you mean task.stages.s0.lr?"),
    "env_id": ("task.env.env_id=CartPole-v1", "Fix: did you mean task=gym?"),
    "added_env_id": ("+task.env.env_id=CartPole-v1", "Fix: did you mean task=gym?"),
    # refused by Hydra itself, said as the package's own refusals are
    "root_key": ("nokey=1", "Key 'nokey' not in 'TrainConfig'"),
    "added_root_key": ("+eval.episode=3", "Fix: did you mean eval.episodes?"),
    "type": ("task.stages.s0.lr=abc", "'abc' of type 'str' could not be converted to Float"),
    "group_option": ("task=nope", "Available options in 'task': cargo, custom, gridworld"),
}
# a refused run's directory: one it makes (with its parents), one of the user's
REFUSED_DIRS = {"new": "new/date/time", "existing": "existing"}
LINE = ["task.env.env_id=line_env:LineWorld-v0", "task.env.stage_fn._target_=line_env.line_stage"]
SHOW_CFG = {  # stages-train ... --cfg job
    "gym": ["task=gym", *LINE, "task.stages.s1.frames=4096"],
    "gym_bare": ["task=gym"],
}

# which fixture needs which independent commands (started together, up front)
NEEDS = {
    "smoke": ["smoke"],
    "multirun": ["multirun"],
    "bad_runs": [f"bad:{name}" for name in BAD_OVERRIDES],
    "refused": [f"refused:{name}" for name in REFUSED_DIRS],
    "shown": [f"cfg:{name}" for name in SHOW_CFG],
}


@pytest.fixture(scope="module", autouse=True)
def commands(tmp_path_factory, request):
    """Starts, at once, every command that the selected tests of this module will read."""
    selected = [
        item for item in request.session.items if getattr(item, "module", None) is request.module
    ]
    used = {name for item in selected for name in item.fixturenames}
    cmds = Commands(tmp_path_factory.mktemp("cli"), used)
    try:
        for fixture, names in NEEDS.items():
            if fixture in used:
                for name in names:
                    cmds.start(name)
        yield cmds
    finally:
        cmds.stop_all()


@pytest.fixture(scope="module")
def smoke(commands) -> tuple[Result, Path]:
    """The finished tiny training run: (its result, its run directory)."""
    result = commands.result("smoke")
    assert result.returncode == 0, result.output[-4000:]
    if "reeval" in commands.used:
        commands.start("reeval")  # runs while the in-process tests read the run
    return result, commands.root / "run"


@pytest.fixture(scope="module")
def run_dir(smoke) -> Path:
    return smoke[1]


@pytest.fixture(scope="module")
def eval_json(run_dir) -> dict:
    return json.loads((run_dir / "eval.json").read_text())


@pytest.fixture(scope="module")
def reeval(commands, run_dir) -> tuple[Result, Path]:
    """``stages-eval --no-plots --episodes 3`` on a copy of the finished run (figures deleted)."""
    return commands.result("reeval"), commands.root / "reeval"


@pytest.fixture(scope="module")
def multirun(commands) -> tuple[Result, Path]:
    return commands.result("multirun"), commands.root / "multi"


@pytest.fixture(scope="module")
def bad_runs(commands) -> dict[str, tuple[Result, Path]]:
    return {
        name: (commands.result(f"bad:{name}"), commands.root / "bad" / name)
        for name in BAD_OVERRIDES
    }


@pytest.fixture(scope="module")
def refused(commands) -> dict[str, Result]:
    return {name: commands.result(f"refused:{name}") for name in REFUSED_DIRS}


@pytest.fixture(scope="module")
def shown(commands) -> dict[str, Result]:
    return {name: commands.result(f"cfg:{name}") for name in SHOW_CFG}


def _read_metrics(path: Path) -> list[list[str]]:
    with path.open(newline="") as f:
        return list(csv.reader(f))


# ------------------------------------------------------------------ stages-train: one tiny run
def test_console_scripts_are_installed():
    for name in ("stages-train", "stages-eval"):
        assert os.access(console_script(name), os.X_OK)


def test_train_prints_the_run_directory(smoke):
    result, run_dir = smoke
    assert f"Run directory: {run_dir}" in result.stdout
    assert "task gridworld: success" in result.stdout
    assert "Traceback" not in result.stderr
    # and what in it a user wants: eval.json and the figures
    end = result.stdout[result.stdout.index(f"Run directory: {run_dir}") :].splitlines()
    assert end[1] == f"  eval.json: {run_dir / 'eval.json'}"
    figures = [line.removeprefix("  figure: ") for line in end[2:]]
    assert figures == [str(path) for path in sorted(run_dir.glob("*.png"))]
    assert str(run_dir / "value_map.png") in figures


def test_train_logs_every_stage_evaluation_where_no_bar_is_shown(smoke):
    # the command's stderr is a pipe, not a terminal: one line per stage evaluation, on the
    # console and in the run's log file, where a progress bar would be
    result, run_dir = smoke
    logged = (run_dir / "stages-train.log").read_text()
    for k in range(NUM_STAGES):
        line = f"stage {k} (s{k}): {FRAMES} of {FRAMES} frames, success "
        assert line in result.stdout and line in logged, k


def test_train_writes_nothing_outside_the_run_dir(commands, smoke):
    # hydra.run.dir is honoured: no ./outputs (or ./multirun) in the working directory
    assert not (commands.root / "outputs").exists()
    assert not (commands.root / "multirun").exists()


def test_run_dir_contents(run_dir):
    expected = [
        "config.yaml",
        ".hydra/config.yaml",
        ".hydra/overrides.yaml",
        *[f"stage_{k}.pt" for k in range(NUM_STAGES)],
        "metrics.csv",
        "eval.json",
        "value_map.npy",
        "trajectories.png",
        "value_map.png",
    ]
    for name in expected:
        assert (run_dir / name).is_file(), f"{name} missing from {sorted(os.listdir(run_dir))}"
    for png in ("trajectories.png", "value_map.png"):
        assert_figure(run_dir / png)


def test_saved_config_is_resolved_and_has_the_overrides(run_dir):
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert saved["task"]["name"] == "gridworld"
    assert saved["logger"]["exp_name"] == "gridworld"  # ${task.name} resolved
    assert list(saved["task"]["stages"]) == [f"s{k}" for k in range(NUM_STAGES)]
    for stage in saved["task"]["stages"].values():
        assert stage["frames"] == FRAMES and stage["num_envs"] == 16
        assert stage["algo"] == "dqn" and stage["gamma"] == 0.99
    hydra_saved = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())
    assert hydra_saved["task"]["stages"] == saved["task"]["stages"]


def test_stage_checkpoints(run_dir):
    for k in range(NUM_STAGES):
        state = torch.load(run_dir / f"stage_{k}.pt")
        assert state["stage"] == k and state["name"] == f"s{k}" and state["algo"] == "dqn"
        assert state["result"]["frames"] == FRAMES


def test_metrics_csv(run_dir):
    rows = _read_metrics(run_dir / "metrics.csv")
    assert rows[0] == ["name", "step", "value"]
    names = {row[0] for row in rows[1:]}
    for k in range(NUM_STAGES):
        assert f"eval/stage_{k}/success_rate" in names
        assert any(name.startswith(f"train/stage_{k}/") for name in names)
    assert "train/stage_4/loss" in names
    assert "eval/final/success_rate" in names
    # eval.probe=true: every evaluation of stage 0, the last stage trained, follows the whole task
    probed = {row[0]: int(row[1]) for row in rows[1:] if row[0].startswith("eval/task/")}
    assert probed.keys() == {f"eval/task/{m}" for m in PROBED}
    assert set(probed.values()) == {FRAMES * NUM_STAGES}  # against the frames of all stages
    for name, step, value in rows[1:]:
        assert name.split("/")[0] in ("train", "eval"), name
        int(step)
        float(value)
    # stages train backwards: the last stage's rows come first
    first_stage_rows = [row[0] for row in rows[1:] if row[0].startswith("train/")]
    assert first_stage_rows[0].startswith("train/stage_4/")


def test_eval_json(eval_json):
    for key in ("success_rate", "mean_return", "mean_steps", "task_metrics"):
        assert key in eval_json, key
    assert eval_json["task"] == "gridworld"
    # the grid world enumerates its whole-task starts: one episode from every column-0 cell
    assert eval_json["episodes"] == 25 and eval_json["starts"] == "all"
    assert 1 <= eval_json["mean_steps"] <= MAX_STEPS
    assert sum(eval_json["mean_steps_per_stage"]) == pytest.approx(eval_json["mean_steps"])
    metrics = eval_json["task_metrics"]
    path = metrics["path_from_origin"]
    assert path[0] == [0, 0]
    assert all(len(cell) == 2 for cell in path)
    moves = metrics["vertical_moves_per_stage"]
    assert len(moves) == NUM_STAGES and all(m >= 0 for m in moves)
    stages = eval_json["training"]["stages"]
    assert len(stages) == NUM_STAGES
    assert all(stage["frames"] == FRAMES for stage in stages)


def test_value_map(run_dir):
    values = np.load(run_dir / "value_map.npy")
    assert values.shape == (25, 25)
    assert np.isfinite(values).all()


# ------------------------------------------------------------------ the trained run, in-process
def test_load_policy_returns_a_stacked_policy(run_dir):
    policy = load_policy(run_dir)
    assert isinstance(policy, StackedPolicy)
    assert len(policy.policies) == NUM_STAGES


def test_loaded_policy_drives_task_env_rollouts(run_dir):
    run = load_run(run_dir)
    assert isinstance(run.task, StagedTask)
    assert run.task.num_stages == NUM_STAGES
    policy = load_policy(run_dir)
    env = run.task.task_env(4)
    with torch.no_grad():
        rollout = env.rollout(30, policy, break_when_any_done=False)
    assert rollout.batch_size == torch.Size([4, 30])
    stage = rollout["stage"]
    assert ((stage >= 0) & (stage < NUM_STAGES)).all()
    action = rollout["action"]
    if action.shape[-1] == 4:  # one-hot
        action = action.argmax(-1)
    assert ((action >= 0) & (action < 4)).all()


def test_stacked_policy_routes_each_element_to_its_stage(run_dir):
    run = load_run(run_dir)
    policy = load_policy(run_dir)
    td = run.task.task_env(16).reset()
    with torch.no_grad():
        for k, learner in enumerate(run.learners):
            tagged = td.clone()
            tagged["stage"] = torch.full_like(td["stage"], k)
            expected = learner.policy(tagged.clone())["action"]
            assert torch.equal(policy(tagged.clone())["action"], expected), f"stage {k}"


def test_loaded_policy_reproduces_the_greedy_path(run_dir, eval_json):
    task = load_run(run_dir).task
    policy = load_policy(run_dir)
    assert greedy_path(task, policy, (0, 0)) == eval_json["task_metrics"]["path_from_origin"]


# ------------------------------------------------------------------ stages-eval
def test_eval_reevaluates_a_run(reeval, eval_json):
    result, directory = reeval
    assert result.returncode == 0, result.output[-4000:]
    assert f"Run directory: {directory}" in result.stdout
    again = json.loads((directory / "eval.json").read_text())
    # the evaluation of the reloaded run (every column-0 start, greedy path, value map) is the
    # one made right after training: the checkpoints restore the greedy policies exactly
    assert {k: v for k, v in again.items() if k != "training"} == {
        k: v for k, v in eval_json.items() if k != "training"
    }
    assert not list(directory.glob("*.png"))  # --no-plots


# The failures of stages-eval are checked in-process (`cli.evaluate(argv)`, what the console
# script calls): each saves a subprocess start-up, and the exit code is the SystemExit code.
def _eval_fails(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        stages_eval_main([str(a) for a in argv])
    assert info.value.code not in (0, None)
    err = capsys.readouterr().err
    assert "stages-eval" in err  # its own message (or argparse's usage error)
    return err


def test_eval_without_a_stage_checkpoint_fails(run_dir, tmp_path, capsys):
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    (copy / "stage_2.pt").unlink()
    err = _eval_fails([copy], capsys)
    assert "stage_2.pt" in err
    assert "stage_1.pt" not in err and "stage_3.pt" not in err
    assert json.loads((copy / "eval.json").read_text()) == json.loads(
        (run_dir / "eval.json").read_text()
    )  # nothing rewritten


def test_eval_of_a_directory_that_is_not_a_run_fails(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a run\n")
    err = _eval_fails([tmp_path], capsys)
    assert "not a torchrl-stages run directory" in err
    assert "config.yaml" in err


def test_eval_of_a_missing_directory_fails(tmp_path, capsys):
    err = _eval_fails([tmp_path / "no_such_run"], capsys)
    assert "no_such_run" in err


def test_eval_rejects_zero_episodes(run_dir, tmp_path, capsys):
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    err = _eval_fails([copy, "--episodes", "0", "--no-plots"], capsys)
    assert "episodes" in err


# ------------------------------------------------------------------ invalid configs
@pytest.mark.parametrize("name", list(BAD_OVERRIDES))
def test_invalid_config_fails_before_training(bad_runs, name):
    result, run_dir = bad_runs[name]
    assert result.returncode == 2, result.output[-2000:]
    assert not run_dir.exists()  # nothing written: not even the directory Hydra made
    assert "Traceback" not in result.stderr and "HYDRA_FULL_ERROR" not in result.stderr
    _, key = BAD_OVERRIDES[name]
    lines = [line for line in result.stderr.splitlines() if line.startswith("stages-train:")]
    assert len(lines) == 1 and key in lines[0], result.stderr[-2000:]
    assert "invalid config" in lines[0] and "Fix:" in lines[0]


def test_a_run_directory_hydra_cannot_make_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "file").write_text("")
    monkeypatch.setattr(sys, "argv", ["stages-train", f"hydra.run.dir={tmp_path / 'file'}"])
    # Hydra points the root logger at this test's captured stdout, closed once it ends
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])
    monkeypatch.setattr(root, "level", root.level)
    with pytest.raises(SystemExit) as exited:
        cli.train()
    err = capsys.readouterr().err
    assert exited.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"stages-train: cannot write {tmp_path / 'file'}") and "Fix:" in err


def test_a_refused_run_leaves_the_directories_it_made_and_keeps_the_users(commands, refused):
    for result in refused.values():
        assert result.returncode == 2, result.output[-2000:]
        assert "task.stages.s0.gamma=1.5" in result.stderr
    assert not (commands.root / "new").exists()  # made with its parents: all gone
    existing = commands.root / REFUSED_DIRS["existing"]
    assert [p.name for p in existing.iterdir()] == ["notes.txt"]  # the user's: kept as it was
    assert (existing / "notes.txt").read_text() == "mine\n"


def test_cfg_job_shows_the_stages_of_a_template_task(shown):
    result = shown["gym"]
    assert result.returncode == 0, result.output[-2000:]
    stages = yaml.safe_load(result.stdout)["task"]["stages"]
    assert list(stages) == ["s0", "s1"]  # LineWorld's num_stages
    assert stages["s1"]["frames"] == 4096 and stages["s1"]["algo"] == "dqn"
    assert (
        stages["s0"]["frames"] == yaml.safe_load(result.stdout)["task"]["stage_template"]["frames"]
    )
    # without the env, it says where the stages come from (the output stays YAML)
    bare = shown["gym_bare"]
    assert bare.returncode == 0, bare.output[-2000:]
    assert yaml.safe_load(bare.stdout)["task"]["stages"] == {}
    line = next(line for line in bare.stdout.splitlines() if line.strip().startswith("stages:"))
    assert "num_stages" in line and "task.env.env_id" in line, line


# ------------------------------------------------------------------ multirun sweep
def test_multirun_over_seeds_and_gammas(multirun):
    result, sweep_dir = multirun
    assert result.returncode == 0, result.output[-4000:]
    jobs = sorted(p.parent for p in sweep_dir.glob("*/eval.json"))
    assert len(jobs) == 4, sorted(os.listdir(sweep_dir))
    assert (sweep_dir / "multirun.yaml").is_file()
    combos = set()
    for job in jobs:
        saved = yaml.safe_load((job / "config.yaml").read_text())
        gammas = [stage["gamma"] for stage in saved["task"]["stages"].values()]
        assert gammas in (HOMO, HETERO), gammas
        combos.add((saved["seed"], "hetero" if gammas == HETERO else "homo"))
        assert all((job / f"stage_{k}.pt").is_file() for k in range(NUM_STAGES))
        assert not list(job.glob("*.png"))  # eval.plots=false
        assert f"Run directory: {job}" in result.stdout
    assert combos == {(0, "homo"), (0, "hetero"), (1, "homo"), (1, "hetero")}
