"""``stages-tune``: an Optuna study of ``stages-train`` runs (``torchrl_stages.tune``).

A 4-trial study with SQLite storage and the median pruner on a two-stage 10 x 10 grid world at
the smoke budget, then the same command again (the study goes on, its fifth trial pruned for
sure by a threshold no stage evaluation reaches); a run pruned in-process at its first stage
evaluation; and search spaces that fail before any training, naming the key. The studies need
Optuna (``pip install -e ".[tune]"``) and are skipped, with that reason, without it.
"""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import hydra
import pytest
import yaml
from helpers import Launched, hydra_config, run_cli

from torchrl_stages.config import ConfigError
from torchrl_stages.loggers import StopRun
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.tune import StudyContext, TrialPruning, run_study

HAS_OPTUNA = importlib.util.find_spec("optuna") is not None
needs_optuna = pytest.mark.skipif(
    not HAS_OPTUNA, reason='optuna is not installed (pip install -e ".[tune]")'
)

#: two stages (s0, s1) of a 10 x 10 grid at the smoke budget: two evaluations per stage
TINY = [
    "experiment=smoke",
    "task.env.size=10",
    "task.env.num_stages=2",
    "~task.stages.s2",
    "~task.stages.s3",
    "~task.stages.s4",
    "eval.plots=false",
    "progress=false",
]
SPACE = "tune.params={task.stages.s1.lr: {low: 1e-4, high: 1e-2, log: true}}"
STUDY = [*TINY, SPACE, "tune.study_name=lr", "tune.plots=false", "tune.startup_trials=1"]
BAD_KEY = "+tune.params={task.stages.s1.lrr: {low: 1e-4, high: 1e-2}}"


def _load(cwd: Path):
    import optuna

    return optuna.load_study(study_name="lr", storage=f"sqlite:///{cwd / 'study.db'}")


def _statuses(study_dir: Path) -> list[str]:
    with (study_dir / "summary.csv").open(newline="") as handle:
        return [row["status"] for row in csv.DictReader(handle)]


@pytest.fixture(scope="module")
def bad_key(tmp_path_factory):
    """``stages-tune`` with a search-space key the config lacks, started at once (it runs
    beside the study); yields its launch directory and ``wait()`` -> (exit code, stdout +
    stderr)."""
    cwd = tmp_path_factory.mktemp("bad_key")
    proc = Launched(["stages-tune", *TINY, BAD_KEY, "tune.study_name=bad"], cwd)

    def wait() -> tuple[int, str]:
        result = proc.result()
        return result.returncode, result.stdout + result.stderr

    yield cwd, wait
    proc.stop()


@pytest.fixture(scope="module")
def study(tmp_path_factory, bad_key):
    """The first command (4 trials), then the same command with one more trial that a
    threshold pruner stops at its first stage evaluation; returns the launch directory."""
    cwd = tmp_path_factory.mktemp("tune")
    first = run_cli(["stages-tune", *STUDY, "tune.n_trials=4"], cwd)
    again = run_cli(
        ["stages-tune", *STUDY, "tune.n_trials=1", "tune.pruner=threshold", "tune.prune_below=1"],
        cwd,
    )
    return cwd, first, again


@pytest.mark.e2e
@pytest.mark.slow
@needs_optuna
def test_study_trials_are_runs_with_a_summary_and_the_best(study):
    cwd, first, _ = study
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    import optuna

    study_dir = cwd / "tune" / "lr"  # hydra.run.dir; the storage is where it was launched
    trials = _load(cwd).get_trials(deepcopy=False)[:4]
    assert [t.number for t in trials] == [0, 1, 2, 3]
    assert trials[0].state == optuna.trial.TrialState.COMPLETE  # nothing to compare it with
    for trial in trials:
        run = study_dir / str(trial.number)
        overrides = yaml.safe_load((run / ".hydra" / "overrides.yaml").read_text())
        lr = trial.params["task.stages.s1.lr"]
        assert 1e-4 <= lr <= 1e-2 and f"task.stages.s1.lr={lr!r}" in overrides
        if trial.state == optuna.trial.TrialState.COMPLETE:
            assert trial.value == json.loads((run / "eval.json").read_text())["success_rate"]
        else:
            assert trial.state == optuna.trial.TrialState.PRUNED, trial.state
            assert json.loads((run / "status.json").read_text())["status"] == "pruned"
    for name in ("summary.csv", "summary.md", "summary_configs.csv"):
        assert (study_dir / name).is_file()
    best = yaml.safe_load((study_dir / "best.yaml").read_text())
    assert best["trials"]["complete"] >= 1 and best["objective"]["metric"] == "success_rate"
    complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    top = max(complete, key=lambda t: (t.value, -t.number))
    assert best["best"]["number"] == top.number and best["best"]["value"] == top.value
    assert best["best"]["params"] == top.params
    assert f"Best trial {top.number}: success_rate=" in first.stdout


@pytest.mark.e2e
@pytest.mark.slow
@needs_optuna
def test_the_same_command_continues_the_study_and_a_pruned_trial_stops_early(study):
    cwd, _, again = study
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    import optuna

    trials = _load(cwd).get_trials(deepcopy=False)
    assert len(trials) == 5
    assert trials[4].state == optuna.trial.TrialState.PRUNED
    run = cwd / "tune" / "lr" / "4"
    status = json.loads((run / "status.json").read_text())
    assert status["status"] == "pruned" and "stage evaluation 0" in status["reason"]
    assert not (run / "eval.json").exists() and not (run / "stage_1.pt").exists()
    rows = (run / "metrics.csv").read_text().splitlines()
    assert sum(r.startswith("eval/stage_1/success_rate,") for r in rows) == 1
    assert not any(r.startswith("eval/stage_0/") for r in rows)  # stage 0 never started
    assert _statuses(cwd / "tune" / "lr")[4] == "pruned"  # the summary lists all 5


@pytest.mark.e2e
@pytest.mark.slow
def test_a_key_not_in_the_config_fails_before_training(bad_key):
    cwd, wait = bad_key
    code, output = wait()
    assert code == 2, output[-3000:]
    assert "stages-tune: invalid config: tune.params.task.stages.s1.lrr: no such key" in output
    assert "Fix: check its spelling" in output
    assert not (cwd / "study.db").exists() and not (cwd / "tune" / "bad" / "0").exists()


class _Trial:
    """What :class:`TrialPruning` uses of an ``optuna.Trial``: prunes from the first report."""

    def __init__(self) -> None:
        self.reported: list[tuple[int, float]] = []

    def report(self, value: float, step: int) -> None:
        self.reported.append((step, value))

    def should_prune(self) -> bool:
        return True


def test_a_pruned_run_stops_at_its_first_stage_evaluation(compose_cfg, tmp_path):
    trial = _Trial()
    cfg = compose_cfg(*TINY, "task.stages.s1.frames=4096", "all_stages.eval_every=512")
    with pytest.raises(StopRun, match="pruned at stage evaluation 0"):
        Experiment(cfg, tmp_path / "run", observers=[TrialPruning(trial)]).run()
    run = tmp_path / "run"
    assert json.loads((run / "status.json").read_text())["status"] == "pruned"
    assert [step for step, _ in trial.reported] == [0]
    rows = [r.split(",") for r in (run / "metrics.csv").read_text().splitlines()[1:]]
    assert max(int(step) for _, step, _ in rows) == 512  # nothing after the evaluation
    assert {name for name, _, _ in rows if name.startswith("eval/")} >= {
        "eval/stage_1/success_rate",
        "eval/stage_1/value_error",  # the evaluation is logged whole
    }
    assert not (run / "eval.json").exists() and not (run / "stage_1.pt").exists()


def test_a_minimized_objective_is_reported_as_the_failure_rate():
    trial = _Trial()
    with pytest.raises(StopRun):
        TrialPruning(trial, "minimize")({"eval/joint_2/success_rate": 0.75}, 64)
    assert trial.reported == [(0, 0.25)]


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ("{task.stages.s9.lr: {low: 1e-4, high: 1e-2}}", r"tune\.params\.task\.stages\.s9\.lr: "),
        ("{task.stages.s1.lr: {low: 1e-4, hi: 1e-2}}", r"s1\.lr=.*unknown hi"),
        ("{task.stages.s1.lr: {low: 0, high: 1e-2, log: true}}", r"s1\.lr\.low=0: must be > 0"),
        ("{task.stages.s1.num_envs: {low: 0.5, high: 2.5}}", r"num_envs=0\.5 does not fit"),
        ("{task.stages.s1.lr: {low: -1.0, high: 1.0}}", r"lr=-1\.0 makes an invalid config"),
        ("{algo@task.stages.s0: {choices: [dqn, nope]}}", r"s0: a config group takes choices"),
        ("{task.stages: {low: 1, high: 2}}", r"names a block of keys"),
        ("{}", r"tune\.params=None: the search space is empty"),
    ],
)
def test_a_bad_search_space_fails_before_any_training(tmp_path, params, message):
    overrides = [*TINY, f"+tune.params={params}"] if params != "{}" else TINY
    with hydra_config():
        cfg = hydra.compose("tune", overrides=overrides)
        context = StudyContext(
            tmp_path / "study",
            tmp_path,
            overrides,
            lambda o: hydra.compose("config", overrides=o),
        )
        with pytest.raises(ConfigError, match=message):
            run_study(cfg, context)
    assert list(tmp_path.iterdir()) == []  # no storage, no study directory


def test_values_overrides_and_storage_as_written_on_the_command_line():
    from torchrl_stages.tune.space import hydra_value, search_space, train_overrides
    from torchrl_stages.tune.study import storage_location

    values = [hydra_value(v) for v in (3, 0.001, True, None, "sac", "a b")]
    assert values == ["3", "0.001", "true", "null", "sac", "'a b'"]
    space = search_space(
        {
            "task.stages.s3.lr": {"low": 1e-4, "high": 1e-2, "log": True},
            "task": {"stages": {"s2": {"gamma": {"choices": [0.9, 0.99]}}}},
        }
    )
    kinds = [("task.stages.s3.lr", "float"), ("task.stages.s2.gamma", "categorical")]
    assert [(p.name, p.kind) for p in space] == kinds
    overrides = ["experiment=smoke", "tune.n_trials=4", "+tune.params={}", "tune=lr"]
    assert train_overrides(overrides) == ["experiment=smoke"]
    assert storage_location("sqlite:///study.db", "/runs") == "sqlite:////runs/study.db"
    assert storage_location("study.log", "/runs") == "/runs/study.log"
    assert storage_location("postgresql://host/optuna", "/runs") == "postgresql://host/optuna"


def _run_study(tmp_path: Path, *overrides: str) -> int:
    overrides = [*STUDY, *overrides]
    with hydra_config():
        cfg = hydra.compose("tune", overrides=overrides)
        compose = lambda o: hydra.compose("config", overrides=o)  # noqa: E731
        return run_study(cfg, StudyContext(tmp_path / "study", tmp_path, overrides, compose))


def test_a_storage_in_a_missing_directory_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(
        ConfigError, match="storage='sqlite:///missing/study.db': .*missing is not a directory"
    ):
        _run_study(tmp_path, "tune.storage=sqlite:///missing/study.db")
    assert list(tmp_path.iterdir()) == []


@needs_optuna
def test_a_study_counts_only_its_own_trials(tmp_path, monkeypatch, capsys):
    import optuna

    from torchrl_stages.tune.study import TrialFailed

    def failing_beside_another(trial, *args):  # another process finishes a trial meanwhile
        other = optuna.load_study(study_name="lr", storage=f"sqlite:///{tmp_path / 'study.db'}")
        other.add_trial(optuna.trial.create_trial(params={}, distributions={}, value=1.0))
        raise TrialFailed("the env failed")

    monkeypatch.setattr("torchrl_stages.tune.study._run_trial", failing_beside_another)
    assert _run_study(tmp_path, "tune.n_trials=1") == 1  # every trial of this command failed
    out = capsys.readouterr().out
    assert "1 trials run here (0 finished, 0 pruned, 1 failed), 2 in the study" in out
