"""A run directory is untrusted data, and a run fails loudly for the right reason.

In-process tests on one tiny two-stage 10 x 10 grid-world run (trained once per module and
copied): what loading trusts, damaged files, the record of what the package wrote, the lock,
errors that name the env, non-finite values, retrying after a failure, bookkeeping across
launches and the held thread count. ``tests/test_resume.py`` has the subprocess ones (signals,
two processes, kill and resume).
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import shutil
from pathlib import Path

import pytest
import torch
from helpers import TINY_STAGE, hydra_config, tiny_grid
from omegaconf import OmegaConf

from torchrl_stages import threads
from torchrl_stages.checkpoint import CheckpointDamagedError, StageCheckpoints
from torchrl_stages.cli import evaluate
from torchrl_stages.config import ConfigError, register_configs
from torchrl_stages.failures import DivergenceError, EnvError
from torchrl_stages.integrity import DamagedFileError, atomic_write
from torchrl_stages.learners import ALGORITHMS
from torchrl_stages.runs.directory import RunDir
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.layout import RunDirError
from torchrl_stages.runs.loading import load_run
from torchrl_stages.runs.trust import shippedtargets
from torchrl_stages.sweeps import read_job

TINY = {**TINY_STAGE, "frames": 512, "updates_per_batch": 2, "eval_every": 256}
OVERRIDES = [*tiny_grid(TINY), "checkpoint_every=256"]


def compose(*overrides: str):
    with hydra_config() as compose_fn:
        return compose_fn(*OVERRIDES, *overrides)


def train(run_dir: Path, *overrides: str) -> dict:
    cfg = compose(*overrides)  # .hydra/config.yaml as stages-train writes it
    return Experiment(cfg, run_dir, hydra_files={"config.yaml": cfg}).run()[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("faults") / "run"
    train(run_dir)
    return run_dir


@pytest.fixture
def copy(finished, tmp_path):
    """A fresh copy of the finished run."""
    target = tmp_path / "run"
    shutil.copytree(finished, target)
    return target


def one_line_eval(run_dir: Path, capsys, *extra: str) -> str:
    """``stages-eval RUN_DIR`` that must fail with exit 2 and one line; returns it."""
    with pytest.raises(SystemExit) as info:
        evaluate([str(run_dir), "--no-plots", *extra])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def edit_config(run_dir: Path, edit) -> None:
    cfg = OmegaConf.load(run_dir / "config.yaml")
    edit(cfg)
    OmegaConf.save(cfg, run_dir / "config.yaml")


# ---------------------------------------------------------------------- 1. what loading trusts
def test_a_config_naming_other_code_is_refused_and_runs_nothing(copy, tmp_path, capsys):
    marker = tmp_path / "ran"

    def inject(cfg):  # a nested node of the env's keyword arguments
        cfg.task.env.size = {"_target_": "os.makedirs", "name": str(marker)}

    edit_config(copy, inject)
    (copy / ".stages" / "run.json").unlink()  # no checksum to catch the edit
    with pytest.raises(RunDirError, match=r"task\.env\.size\._target_='os\.makedirs'"):
        load_run(copy)
    err = one_line_eval(copy, capsys)
    assert "task.env.size._target_" in err and "--trust" in err
    assert not marker.exists()
    with pytest.raises(RunDirError):  # trusted: the config runs (and then fails to build)
        load_run(copy, trust=True)
    assert marker.is_dir()


def test_a_replaced_env_target_is_refused(copy):
    edit_config(copy, lambda cfg: setattr(cfg.task.env, "_target_", "builtins.exec"))
    (copy / ".stages" / "run.json").unlink()
    with pytest.raises(RunDirError, match="builtins.exec.*torchrl_stages.envs.GridWorldEnv"):
        load_run(copy)


def test_a_run_of_your_own_env_loads_with_trust(copy):
    def custom(cfg):
        cfg.task.name = "custom"

    edit_config(copy, custom)
    (copy / ".stages" / "run.json").unlink()
    with pytest.raises(RunDirError, match="task 'custom'.*trust=True"):
        load_run(copy)
    assert len(load_run(copy, trust=True).learners) == 2


def test_a_shipped_tasks_targets_are_read_without_resolving_it():
    # a loading process need not have the config's resolvers (minigrid's keys depend on the
    # level through one): what the task instantiates is read from its YAML as text
    OmegaConf.clear_resolver("stages_by_prefix")
    try:
        targets = shippedtargets("minigrid")
        assert targets == {"task.env._target_": "torchrl_stages.envs.MiniGridEnv"}
    finally:
        register_configs(ALGORITHMS)


def _pickle_bomb(marker: Path) -> bytes:
    class Bomb:
        def __reduce__(self):
            return (os.makedirs, (str(marker),))

    return pickle.dumps(Bomb())


@pytest.mark.parametrize("name", ["prefetch.pkl", "state.pt", "state/other.pickle"])
def test_a_checkpoint_holding_a_pickle_is_never_unpickled(copy, tmp_path, name):
    marker = tmp_path / "ran"
    ckpts = StageCheckpoints(copy / "checkpoints" / "stage_0", every=1)
    net = torch.nn.Linear(2, 1)
    path = ckpts.save(1, {"net": net, "counters": {"frames": 1}})
    component = next((path / "components").glob("*net"))
    (component / name).parent.mkdir(parents=True, exist_ok=True)
    (component / name).write_bytes(_pickle_bomb(marker))
    fresh = StageCheckpoints(copy / "checkpoints" / "stage_0", every=1)
    with pytest.raises(CheckpointDamagedError, match=name.split("/")[-1]):
        fresh.latest()
    with pytest.raises(CheckpointDamagedError):
        fresh.load(path, {"net": net, "counters": {"frames": 1}})
    assert not marker.exists()


def test_checkpoints_hold_tensors_and_json_only(tmp_path):
    ckpts = StageCheckpoints(tmp_path, every=1)
    path = ckpts.save(1, {"net": torch.nn.Linear(2, 1), "counters": {"frames": 1, "x": [1.5]}})
    suffixes = {p.suffix for p in path.rglob("*") if p.is_file()}
    assert suffixes <= {".json", ".memmap"}, suffixes


# ---------------------------------------------------------------------- 2. what overwrite deletes
def test_overwrite_refuses_a_directory_without_a_record(copy):
    (copy / ".stages" / "run.json").unlink()
    (copy / "notes.png").write_bytes(b"mine")
    before = sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*"))
    with pytest.raises(RunDirError, match=r"overwrite=true: .* no \.stages/run\.json"):
        Experiment(compose("overwrite=true"), copy)
    assert sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*")) == before


def test_overwrite_refuses_run_files_its_record_does_not_list(copy):
    record = json.loads((copy / ".stages" / "run.json").read_text())
    del record["entries"]["stage_1.pt"]
    (copy / ".stages" / "run.json").write_text(json.dumps(record))
    with pytest.raises(RunDirError, match="stage_1.pt, which its record"):
        Experiment(compose("overwrite=true"), copy)
    assert (copy / "stage_1.pt").is_file() and (copy / "config.yaml").is_file()


def test_overwrite_forgets_what_the_replaced_run_recorded(copy):
    record = json.loads((copy / ".stages" / "run.json").read_text())
    record.update(reused={"s0": "a store"}, phases=[{"phase": 0}])  # what launches keep
    (copy / ".stages" / "run.json").write_text(json.dumps(record))
    run_dir = RunDir(copy)
    run_dir.clear()
    kept = json.loads((copy / ".stages" / "run.json").read_text())
    assert kept == {"format": record["format"], "version": 1, "entries": {}, "launches": []}


# ---------------------------------------------------------------------- 3. one writer
def test_a_second_experiment_in_a_held_directory_is_refused(tmp_path):
    first = Experiment(compose(), tmp_path / "run")
    try:
        with pytest.raises(RunDirError, match="in use by another process"):
            Experiment(compose(), tmp_path / "run")
    finally:
        first.close()
    Experiment(compose(), tmp_path / "run").close()  # free again


def test_temporary_files_are_unique_per_process_and_never_left(tmp_path):
    target = tmp_path / "stage_0.pt"
    seen = []

    def fail(tmp: Path) -> None:
        seen.append(tmp.name)
        tmp.write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError) as info:
        atomic_write(target, fail)
    assert info.value.filename == str(target)
    assert str(os.getpid()) in seen[0] and seen[0] != ".stage_0.pt.tmp"
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- 5. damaged state
def test_a_stage_file_holding_text_names_the_file(copy, capsys):
    (copy / "stage_1.pt").write_text("not a checkpoint " * 100)
    (copy / ".stages" / "run.json").unlink()  # no checksum: the content itself is checked
    err = one_line_eval(copy, capsys)
    assert "stage_1.pt is damaged" in err and "resume=true" in err and "KeyError" not in err


def test_a_stage_file_of_another_stage_is_refused(copy, capsys):
    shutil.copy(copy / "stage_0.pt", copy / "stage_1.pt")
    (copy / ".stages" / "run.json").unlink()
    assert "holds stage 0, not stage 1" in one_line_eval(copy, capsys)


def test_a_changed_stage_file_fails_its_checksum(copy, capsys):
    data = bytearray((copy / "stage_1.pt").read_bytes())
    data[-100] ^= 1  # a bit flipped inside the file
    (copy / "stage_1.pt").write_bytes(bytes(data))
    assert "differ from those written" in one_line_eval(copy, capsys)


def test_a_missing_config_is_read_from_hydra_and_restored_on_resume(copy, caplog):
    (copy / "config.yaml").unlink()
    assert len(load_run(copy).learners) == 2
    caplog.clear()
    train(copy, "resume=true")
    assert (copy / "config.yaml").is_file()
    said = [r.getMessage() for r in caplog.records if "config.yaml" in r.getMessage()]
    assert said == [
        f"{copy / 'config.yaml'} is missing: reading {copy / '.hydra/config.yaml'} instead"
    ]


def test_a_full_disk_names_the_path_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    ckpts = StageCheckpoints(tmp_path / "ckpt", every=1)
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=10))
    with pytest.raises(OSError, match="No space left on device") as info:
        ckpts.save(1, {"net": torch.nn.Linear(64, 64)})
    assert str(tmp_path / "ckpt") in info.value.filename
    assert [p.name for p in (tmp_path / "ckpt").iterdir()] == []  # no staging directory


def test_a_read_only_directory_names_the_path_and_loses_nothing(copy, monkeypatch):
    import torchrl_stages.integrity as integrity

    def read_only(src, dst):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(integrity.os, "replace", read_only)
    (copy / "stage_0.pt").unlink()
    before = (copy / "stage_1.pt").read_bytes()
    with pytest.raises(OSError, match="Read-only file system") as info:
        train(copy, "resume=true")
    assert copy in Path(info.value.filename).parents  # the file it could not write
    assert (copy / "stage_1.pt").read_bytes() == before
    assert not [p for p in copy.rglob("*") if p.name.endswith(".tmp")]


# ---------------------------------------------------------------------- 6. the real cause
def test_non_finite_values_are_refused_at_validation():
    for key, value in [("task.stages.s0.lr", "inf"), ("task.stages.s1.gamma", "nan")]:
        with pytest.raises(ConfigError, match=f"{key}={value}: must be a finite number"):
            Experiment(compose(f"{key}={value}"), "never-written")
    assert not Path("never-written").exists()


class NaNAfter:
    """Wraps an env's step: from the ``after``-th call on, the observation is NaN."""

    def __init__(self, after: int, key: str = "observation") -> None:
        self.after, self.key, self.calls = after, key, 0

    def __call__(self, step):
        def wrapped(td):
            out = step(td)
            self.calls += 1
            if self.calls >= self.after:
                out[self.key] = torch.full_like(out[self.key], float("nan"))
            return out

        return wrapped


@pytest.mark.parametrize("key", ["observation", "reward"])
def test_an_env_returning_nan_is_blamed_not_the_learner(tmp_path, monkeypatch, key):
    from torchrl_stages.envs import GridWorldEnv

    patch = NaNAfter(after=20, key=key)
    original = GridWorldEnv._step
    monkeypatch.setattr(GridWorldEnv, "_step", lambda self, td: patch(original.__get__(self))(td))
    run_dir = tmp_path / "run"
    match = f"stage 1 \\(s1\\): the env returned a non-finite (\\('next', )?'{key}'"
    with pytest.raises(EnvError, match=match):
        train(run_dir)
    status = json.loads((run_dir / "status.json").read_text())
    assert status["status"] == "failed" and "non-finite" in status["reason"]
    assert not list(run_dir.glob("stage_*.pt"))


def test_an_env_that_raises_leaves_a_failed_status(tmp_path, monkeypatch):
    from torchrl_stages.envs import GridWorldEnv

    def broken(self, td):
        raise RuntimeError("the simulator lost its license\nserver said: no")

    monkeypatch.setattr(GridWorldEnv, "_step", broken)
    with pytest.raises(RuntimeError):
        train(tmp_path / "run")
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status == {"status": "failed", "reason": "RuntimeError: server said: no"}
    launches = json.loads((tmp_path / "run" / ".stages" / "run.json").read_text())["launches"]
    assert launches[-1]["outcome"] == "failed"
    job = read_job(tmp_path / "run")  # a sweep's summary shows it as failed, with the reason
    assert (job.status, job.reason) == ("failed", "RuntimeError: server said: no")


# ---------------------------------------------------------------------- 7. retry what still holds
def test_after_a_divergence_the_stage_retrains_with_a_changed_key(tmp_path):
    run_dir = tmp_path / "run"
    with pytest.raises(DivergenceError):
        train(run_dir, "task.stages.s0.lr=1e30")
    stage_1 = (run_dir / "stage_1.pt").read_bytes()
    train(run_dir, "resume=true")  # s0's lr back to its default: stage 1 is kept
    assert (run_dir / "stage_1.pt").read_bytes() == stage_1
    assert OmegaConf.load(run_dir / "config.yaml").task.stages.s0.lr == compose().task.stages.s0.lr
    reference = tmp_path / "reference"
    train(reference)
    for k in (0, 1):
        a, b = (torch.load(d / f"stage_{k}.pt", weights_only=True) for d in (run_dir, reference))
        assert all(torch.equal(a["model"][n], b["model"][n]) for n in a["model"])


def test_a_finished_stage_keeps_its_config(copy):
    with pytest.raises(RunDirError, match=r"task\.stages\.s1\.lr; a resumed run keeps"):
        Experiment(compose("task.stages.s1.lr=0.5", "resume=true"), copy)
    with pytest.raises(RunDirError, match=r"in seed"):
        Experiment(compose("seed=4", "resume=true"), copy)


# ---------------------------------------------------------------------- 8. bookkeeping
def test_resuming_a_finished_run_logs_its_final_rows_once(copy):
    metrics = (copy / "metrics.csv").read_text()
    train(copy, "resume=true")
    assert (copy / "metrics.csv").read_text() == metrics
    assert metrics.count("eval/final/success_rate") == 1


def test_every_launch_is_counted_and_re_evaluation_keeps_training(copy, capsys):
    before = json.loads((copy / "eval.json").read_text())["training"]
    train(copy, "resume=true")
    training = json.loads((copy / "eval.json").read_text())["training"]
    assert len(training["launches"]) == 2 == len(before["launches"]) + 1
    assert training["seconds"] == pytest.approx(sum(x["seconds"] for x in training["launches"]))
    assert training["seconds"] >= before["seconds"]
    evaluate([str(copy), "--no-plots"])
    capsys.readouterr()
    assert json.loads((copy / "eval.json").read_text())["training"] == training


# ---------------------------------------------------------------------- 9. threads held
def _close_a_batched_env() -> None:
    """What torchrl does when a batched env closes (also when one is garbage-collected in the
    middle of a stage): ``torch.set_num_threads`` to more threads (how many depends on the
    machine and ``OMP_NUM_THREADS``: 2 here)."""
    from torchrl.envs import SerialEnv

    from torchrl_stages.envs import GridWorldEnv

    env = SerialEnv(2, lambda: GridWorldEnv((1,), size=10, num_stages=2))
    env.rollout(1)
    env.close()
    torch.set_num_threads(2)


@pytest.mark.slow
@pytest.mark.parametrize("schedule", ["backward", "joint"])
def test_the_thread_count_is_held_in_every_update_and_evaluation(tmp_path, monkeypatch, schedule):
    from torchrl_stages import evaluate as evaluation
    from torchrl_stages.learners.dqn import DQNLearner as Learner

    seen = {"update": [], "evaluation": []}
    update, rollout = Learner.update, evaluation.rollout_first_episodes

    def spy_update(self, sample):
        seen["update"].append(torch.get_num_threads())
        out = update(self, sample)
        _close_a_batched_env()
        return out

    def spy_rollout(*args, **kwargs):
        seen["evaluation"].append(torch.get_num_threads())
        out = rollout(*args, **kwargs)
        _close_a_batched_env()
        return out

    monkeypatch.setattr(Learner, "update", spy_update)
    monkeypatch.setattr("torchrl_stages.evaluate.rollout_first_episodes", spy_rollout)
    _close_a_batched_env()
    assert torch.get_num_threads() == 2  # the effect held against
    Experiment(compose("threads=1", f"schedule={schedule}"), tmp_path / "run").run()
    assert len(seen["update"]) > 10 and len(seen["evaluation"]) >= 2
    assert set(seen["update"]) == {1} and set(seen["evaluation"]) == {1}
    torch.set_num_threads(1)


def test_hold_threads_puts_the_count_back():
    with threads.hold_threads(1):
        torch.set_num_threads(2)
        threads.keep_threads()
        assert torch.get_num_threads() == 1
    threads.keep_threads()  # nothing held: no-op


# ---------------------------------------------------------------------- 4. signals, in process
def test_a_signal_checkpoints_then_hands_over_to_the_handler_before(finished, tmp_path):
    import signal

    from torchrl_stages.learners.dqn import DQNLearner
    from torchrl_stages.preemption import Interrupted

    run_dir, seen, calls = tmp_path / "run", [], []
    update = DQNLearner.update

    def signalling_update(self, sample):
        calls.append(1)
        if len(calls) == 3:  # in the middle of stage 1 (its 6 updates come first)
            os.kill(os.getpid(), signal.SIGUSR1)
        return update(self, sample)

    def launcher(signum, frame):  # e.g. submitit's requeue: it finds the state saved
        checkpoints = list((run_dir / "checkpoints").rglob("frames-*"))
        status = json.loads((run_dir / "status.json").read_text())
        seen.append((signum, bool(checkpoints), status["status"], status["signal"]))

    previous = signal.signal(signal.SIGUSR1, launcher)
    try:
        DQNLearner.update = signalling_update
        with pytest.raises(Interrupted, match="SIGUSR1 in stage 1 \\(s1\\)") as info:
            train(run_dir, "checkpoint_every=0")
    finally:
        DQNLearner.update = update
        signal.signal(signal.SIGUSR1, previous)
    assert info.value.exit_code == 128 + signal.SIGUSR1
    assert seen == [(signal.SIGUSR1, True, "interrupted", "SIGUSR1")]
    train(run_dir, "checkpoint_every=0", "resume=true")
    for k in (0, 1):
        a, b = (torch.load(d / f"stage_{k}.pt", weights_only=True) for d in (run_dir, finished))
        assert all(torch.equal(a["model"][n], b["model"][n]) for n in a["model"])


def test_a_deleted_stage_file_retrains_it_and_the_stages_after_it_keeping_every_row(copy, caplog):
    rows = (copy / "metrics.csv").read_text()
    (copy / "stage_1.pt").unlink()  # stage 0 was trained against it: it trains again too
    with caplog.at_level("INFO", logger="torchrl_stages"):
        train(copy, "resume=true")
    assert "finished earlier" not in caplog.text
    assert (copy / "metrics.csv").read_text() == rows  # each row once, in the order written


def test_a_metrics_file_cut_short_is_refused_on_resume_and_left_as_it_is(copy):
    metrics = copy / "metrics.csv"
    rows = metrics.read_bytes()
    metrics.write_bytes(rows[: len(rows) // 2])  # cut mid-row: the rows of stage 0 are lost
    cut = metrics.read_bytes()
    with pytest.raises(DamagedFileError, match="metrics.csv: .* rows were lost. Fix: restore"):
        train(copy, "resume=true")
    assert metrics.read_bytes() == cut  # not padded with NUL bytes to its old length


def test_stages_eval_holding_a_run_says_it_is_the_holder(copy, monkeypatch, capsys):
    lock = copy / ".stages" / "lock"
    lock.write_text("process 1 on elsewhere since 2020-01-01T00:00:00: stages-train")  # ended
    seen = []

    def evaluate_run(*args, **kwargs):
        seen.append(lock.read_text())
        raise OSError(errno.EIO, "stop here", str(copy))

    monkeypatch.setattr("torchrl_stages.cli.evaluate_run", evaluate_run)
    one_line_eval(copy, capsys)
    assert seen and seen[0].startswith(f"process {os.getpid()} on "), seen


# ---------------------------------------------------------------------- hostile files, continued
@pytest.mark.parametrize("file", ["config.yaml", ".hydra/config.yaml"])
@pytest.mark.parametrize("value", ["oc.create", "escaped", "oc.env"])
def test_an_interpolation_in_a_run_s_config_is_refused_unresolved(
    copy, tmp_path, monkeypatch, value, file
):
    monkeypatch.setenv("SECRET", "s3cr3t")
    marker = tmp_path / "ran"
    create = f"${{oc.create:{{_target_: os.makedirs, name: {marker}}}}}"
    interpolation = {"oc.create": create, "escaped": "\\" + create, "oc.env": "${oc.env:SECRET}"}
    text = (copy / file).read_text()
    assert "size: 10" in text
    (copy / file).write_text(text.replace("size: 10", f"size: '{interpolation[value]}'", 1))
    (copy / ".stages" / "run.json").unlink()
    if file != "config.yaml":  # read in its place, references to other keys and all
        (copy / "config.yaml").unlink()
    with pytest.raises(RunDirError, match="size holds an interpolation") as refused:
        load_run(copy)
    assert not marker.exists() and "s3cr3t" not in str(refused.value)


def test_a_linked_checkpoints_directory_is_refused_and_nothing_is_deleted(copy, tmp_path):
    victim = tmp_path / "victim"
    (victim / "stage_0").mkdir(parents=True)
    (victim / "stage_0" / "keep.txt").write_text("mine")
    (copy / "checkpoints").symlink_to(victim, target_is_directory=True)
    with pytest.raises(RunDirError, match="checkpoints is a symbolic link"):
        Experiment(compose("resume=true"), copy)
    with pytest.raises(RunDirError, match="symbolic link"):
        RunDir(copy).clear_checkpoints(0)
    (copy / "checkpoints").unlink()
    (copy / "csv" / "deep").mkdir()
    (copy / "csv" / "deep" / "linked").symlink_to(victim, target_is_directory=True)
    with pytest.raises(RunDirError, match="deep/linked is a symbolic link"):
        RunDir(copy).clear_checkpoints(0)
    assert (victim / "stage_0" / "keep.txt").read_text() == "mine"


def test_a_file_kept_as_it_was_when_a_rewrite_was_killed_still_verifies(copy):
    run = RunDir(copy)
    with run.lock():
        run.write_config(OmegaConf.load(copy / "config.yaml"))  # the same bytes: one checksum
        old = (copy / "config.yaml").read_bytes()
        cfg = OmegaConf.load(copy / "config.yaml")
        cfg.eval.plots = True  # a resumed run rewriting its config
        run.write_config(cfg)
    (copy / "config.yaml").write_bytes(old)  # as if killed between the record and the rename
    assert run.read_config().eval.plots is False
    (copy / "config.yaml").write_bytes(old.replace(b"plots: false", b"plots: maybe"))
    with pytest.raises(RunDirError, match="differ from those written"):
        run.read_config()


@pytest.mark.parametrize("edit", ["task: 5", "eval: 3", "schedule: flat"])
def test_a_config_of_the_wrong_shape_is_one_line(copy, capsys, edit):
    key = edit.split(":")[0]
    cfg = OmegaConf.load(copy / "config.yaml")
    cfg[key] = OmegaConf.create(edit)[key]
    OmegaConf.save(cfg, copy / "config.yaml")
    (copy / ".stages" / "run.json").unlink()
    assert "is damaged" in one_line_eval(copy, capsys)


def test_a_damaged_record_is_one_line(copy, capsys):
    record = json.loads((copy / ".stages" / "run.json").read_text())
    record["launches"] = ["x"]
    (copy / ".stages" / "run.json").write_text(json.dumps(record))
    assert "run.json is damaged" in one_line_eval(copy, capsys)


def test_stages_in_another_order_are_refused(copy):
    cfg = OmegaConf.load(copy / "config.yaml")
    stages = cfg.task.stages
    cfg.task.stages = {"s1": stages.s1, "s0": stages.s0}
    OmegaConf.save(cfg, copy / "config.yaml")
    (copy / ".stages" / "run.json").unlink()
    with pytest.raises(RunDirError, match="holds stage 's0', but the run's stage 0 is 's1'"):
        load_run(copy)
    with pytest.raises(RunDirError, match=r"task\.stages \(their order\)"):
        Experiment(compose("resume=true"), copy)


def test_a_stop_during_the_final_evaluation_ends_it_before_the_next_chunk(monkeypatch):
    import signal

    from torchrl_stages import preemption
    from torchrl_stages.evaluate import evaluate_task
    from torchrl_stages.learners import make_learner
    from torchrl_stages.policy import StackedPolicy
    from torchrl_stages.preemption import Interrupted
    from torchrl_stages.runs.experiment import build_task

    task = build_task(compose())
    policy = StackedPolicy([make_learner(task.stage_cfg(k), task.specs(k)).policy for k in (0, 1)])
    monkeypatch.setattr(preemption, "_requested", signal.SIGTERM)
    with pytest.raises(Interrupted, match="the whole-task evaluation"):
        evaluate_task(task, policy, 8, seed=0, interruptible=True)
    assert evaluate_task(task, policy, 8, seed=0).stats.length.numel() == 10  # every start
