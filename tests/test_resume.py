"""Runs that survive faults: SIGKILL and resume, no silent overwrite, damaged files, multiruns.

Every command is a ``stages-train`` process (a fork of one that has imported the package,
which signals reach as they reach any) on a tiny two-stage 10 x 10 grid world with a
checkpoint every 256 frames. The uninterrupted reference run and the run that gets killed start
together (two cores); the other commands are short.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch
from helpers import Launched
from omegaconf import OmegaConf

from torchrl_stages.integrity import write_checksums

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

TIMEOUT_S = 300
TINY = {
    "frames": 2048,
    "frames_per_batch": 128,
    "num_envs": 16,
    "init_random_frames": 128,
    "batch_size": 64,
    "updates_per_batch": 2,
    "eval_every": 512,
    "eval_episodes": 8,
    "min_frames": 0,
}
TWO_STAGES = ["task.env.size=10", "task.env.num_stages=2"] + [
    f"~task.stages.s{k}" for k in (2, 3, 4)
]
OVERRIDES = [
    *TWO_STAGES,
    *[f"task.stages.s{k}.{key}={value}" for k in (0, 1) for key, value in TINY.items()],
    "checkpoint_every=256",
    "eval.plots=false",
    # STAGES_TEST_DEVICE=cuda runs these on a GPU (CI has none)
    f"device={os.environ.get('STAGES_TEST_DEVICE', 'cpu')}",
]


def spawn(run_dir: Path, *extra: str, multirun: bool = False) -> Launched:
    """``stages-train`` in the background: a process of its own, which signals and SIGKILL
    reach as they reach any (a fork of a process that has imported the package)."""
    target = f"hydra.sweep.dir={run_dir}" if multirun else f"hydra.run.dir={run_dir}"
    argv = ["stages-train", *(["-m"] if multirun else []), *OVERRIDES, target, *extra]
    return Launched(argv, run_dir.parent, TIMEOUT_S)


def run(run_dir: Path, *extra: str, multirun: bool = False) -> subprocess.CompletedProcess:
    return spawn(run_dir, *extra, multirun=multirun).result()


def kill_when(proc: Launched, ready, delay: float = 0.0) -> None:
    """SIGKILLs ``proc`` ``delay`` seconds after ``ready()`` first holds."""
    deadline = time.monotonic() + TIMEOUT_S
    while not ready():
        assert proc.poll() is None, "the run ended before it could be killed"
        assert time.monotonic() < deadline
        time.sleep(0.005)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=TIMEOUT_S)
    assert proc.returncode == -signal.SIGKILL


def snapshot(directory: Path) -> dict[str, str]:
    """Every file under ``directory`` (``.hydra/`` included) by content hash."""
    return {
        str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def assert_same_run(a: Path, b: Path) -> None:
    """Bitwise-equal stage weights, identical metrics.csv, eval.json equal but for timings."""
    for k in (0, 1):
        sa, sb = (torch.load(d / f"stage_{k}.pt", weights_only=True) for d in (a, b))
        assert sa["model"].keys() == sb["model"].keys()
        for name in sa["model"]:
            assert torch.equal(sa["model"][name], sb["model"][name]), (k, name)
        for opt in sa["optimizers"]:
            for key, state in sa["optimizers"][opt]["state"].items():
                for field, value in state.items():
                    assert torch.equal(value, sb["optimizers"][opt]["state"][key][field])
    assert (a / "metrics.csv").read_bytes() == (b / "metrics.csv").read_bytes()
    ea, eb = (json.loads((d / "eval.json").read_text()) for d in (a, b))
    timing = ("seconds", "timing")
    for stage_a, stage_b in zip(ea["training"]["stages"], eb["training"]["stages"], strict=True):
        assert {k: v for k, v in stage_a.items() if k not in timing} == {
            k: v for k, v in stage_b.items() if k not in timing
        }
    assert {k: v for k, v in ea.items() if k != "training"} == {
        k: v for k, v in eb.items() if k != "training"
    }


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The uninterrupted reference run, and a run SIGKILLed while stage 1 is in progress
    (after its second checkpoint), started together."""
    root = tmp_path_factory.mktemp("resume")
    reference, killed = root / "reference", root / "killed"
    ref = spawn(reference)
    proc = spawn(killed)
    checkpoints = killed / "checkpoints" / "stage_1"
    kill_when(proc, lambda: len(list(checkpoints.glob("frames-*"))) >= 2, delay=0.05)
    result = ref.result()
    assert result.returncode == 0, result.stderr[-3000:]
    return root, reference, killed


def test_kill_mid_stage_then_resume_is_bitwise_equal(runs):
    root, reference, killed = runs
    assert not (killed / "stage_1.pt").exists()  # killed mid-stage
    assert list((killed / "checkpoints" / "stage_1").glob("frames-*"))
    resumed = root / "mid_stage"
    shutil.copytree(killed, resumed)
    result = run(resumed, "resume=true")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "resuming from" in result.stderr + result.stdout
    assert_same_run(reference, resumed)
    assert not (resumed / "checkpoints").exists()  # dropped once the stages are written
    training = json.loads((resumed / "eval.json").read_text())["training"]
    killed_launch, last = training["launches"]
    assert killed_launch["outcome"] == "running" and killed_launch["seconds"] > 0
    assert training["seconds"] == pytest.approx(killed_launch["seconds"] + last["seconds"])


def test_kill_between_stages_then_resume_is_bitwise_equal(runs):
    root, reference, _ = runs
    # the state a kill leaves between stages: stage 1 written, nothing of stage 0 yet
    between = root / "between"
    shutil.copytree(reference, between)
    for name in ("stage_0.pt", "eval.json", "value_map.npy"):
        (between / name).unlink()
    with (between / "metrics.csv").open("a") as f:  # rows of the interrupted stage 0
        f.write("train/stage_0/loss,128,0.5\n")
    result = run(between, "resume=true")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "finished earlier, loaded" in result.stderr + result.stdout
    assert_same_run(reference, between)


def test_a_directory_with_a_run_is_refused_and_left_untouched(runs):
    _, reference, _ = runs
    before = snapshot(reference)
    result = run(reference, "seed=1")
    assert result.returncode == 2
    assert "resume=true" in result.stderr and "overwrite=true" in result.stderr
    assert snapshot(reference) == before  # .hydra/ included


def test_resume_refuses_overrides_that_change_the_finished_work(runs):
    _, reference, _ = runs
    before = snapshot(reference)
    result = run(reference, "resume=true", "task.stages.s1.lr=0.5", "seed=3")
    assert result.returncode == 2
    assert "seed" in result.stderr and "task.stages.s1.lr" in result.stderr
    assert snapshot(reference) == before


def test_overwrite_replaces_the_run_and_deletes_only_what_it_wrote(runs):
    root, reference, _ = runs
    replaced = root / "replaced"
    shutil.copytree(reference, replaced)
    mine = {  # files of the user's, with the names of a run's files
        "trajectories.png": b"my figure",
        "csv_notes/notes.txt": b"notes",
        ".hydra/mine.yaml": b"a: 1",
    }
    for name, data in mine.items():
        (replaced / name).parent.mkdir(parents=True, exist_ok=True)
        (replaced / name).write_bytes(data)
    (replaced / "metrics.csv").write_text("name,step,value\nstale,0,0\n")
    result = run(replaced, "overwrite=true")
    assert result.returncode == 0, result.stderr[-3000:]
    assert (replaced / "trajectories.png").read_bytes() == b"my figure"
    assert (replaced / "csv_notes" / "notes.txt").read_bytes() == b"notes"
    assert not (replaced / ".hydra" / "mine.yaml").exists()  # .hydra/ is the run's own
    assert_same_run(reference, replaced)  # metrics.csv rewritten from scratch


def test_damaged_stage_checkpoint_names_the_file_and_the_fix(runs, capsys):
    from torchrl_stages.cli import evaluate

    root, reference, _ = runs
    damaged = root / "damaged_stage"
    shutil.copytree(reference, damaged)
    data = (damaged / "stage_1.pt").read_bytes()
    (damaged / "stage_1.pt").write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(SystemExit) as info:
        evaluate([str(damaged), "--no-plots"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "stage_1.pt" in err and "resume=true" in err and "weights_only" not in err
    assert len(err.strip().splitlines()) == 1  # a message, not a traceback
    result = run(damaged, "resume=true")
    assert result.returncode == 2 and "stage_1.pt" in result.stderr
    assert "weights_only" not in result.stderr and "Traceback" not in result.stderr


def test_truncated_config_names_the_file(runs, capsys):
    from torchrl_stages.cli import evaluate

    root, reference, _ = runs
    damaged = root / "damaged_config"
    shutil.copytree(reference, damaged)
    text = (damaged / "config.yaml").read_text()
    (damaged / "config.yaml").write_text(text[: len(text) // 3] + "\n  - [unclosed")
    with pytest.raises(SystemExit):
        evaluate([str(damaged)])
    err = capsys.readouterr().err
    assert "config.yaml" in err and "damaged" in err and "Fix:" in err
    result = run(damaged, "resume=true")
    assert result.returncode == 2 and "config.yaml" in result.stderr
    assert "Traceback" not in result.stderr


def test_invalid_config_leaves_no_new_directory_but_the_hydra_log(tmp_path):
    fresh = tmp_path / "fresh"
    result = run(fresh, "task.stages.s0.gamma=1.5")
    assert result.returncode == 2 and "task.stages.s0.gamma" in result.stderr
    left = [p.name for p in fresh.iterdir()] if fresh.exists() else []
    assert left in ([], ["stages-train.log"])


def test_multirun_survives_an_invalid_job(tmp_path):
    sweep = tmp_path / "sweep"
    result = run(sweep, "task.stages.s0.gamma=0.9,1.5", multirun=True)
    assert result.returncode != 0  # the sweep says that a job failed
    ok, bad = sweep / "0", sweep / "1"
    assert (ok / "eval.json").is_file() and (ok / "stage_0.pt").is_file()
    status = json.loads((bad / "status.json").read_text())
    assert status["status"] == "invalid" and "task.stages.s0.gamma" in status["reason"]
    overrides = (bad / ".hydra" / "overrides.yaml").read_text()
    assert "task.stages.s0.gamma=1.5" in overrides


@pytest.fixture(scope="module")
def joint(tmp_path_factory):
    """The joint schedule's reference run, a run SIGKILLed in its second phase and one stopped
    by SIGTERM in it (no periodic checkpoint: the signal's is its only one), started together."""
    root = tmp_path_factory.mktemp("joint")
    reference, killed, stopped = root / "reference", root / "killed", root / "stopped"
    ref = spawn(reference, "schedule=joint")
    proc = spawn(killed, "schedule=joint")
    term = spawn(stopped, "schedule=joint", "checkpoint_every=0")
    checkpoints, metrics = killed / "checkpoints" / "joint", stopped / "metrics.csv"
    # the second phase (from stage 0) is under way in both: a checkpoint past stage 1's budget
    # exists, a row of phase 0 is logged
    due = {
        "kill": lambda: any(
            int(p.name.split("-")[1]) > TINY["frames"] for p in checkpoints.glob("frames-*")
        ),
        "term": lambda: metrics.is_file() and "train/joint_0/" in metrics.read_text(),
    }
    deadline, stopped_result = time.monotonic() + TIMEOUT_S, None
    while due:
        assert time.monotonic() < deadline
        if "kill" in due and due["kill"]():
            del due["kill"]
            kill_when(proc, lambda: True, delay=0.05)
        if "term" in due and due["term"]():
            del due["term"]
            stopped_result = _stop(term, signal.SIGTERM, 5)
        assert proc.poll() is None or "kill" not in due, "the run ended before it was killed"
        assert term.poll() is None or "term" not in due, "the run ended before it was stopped"
        time.sleep(0.005)
    result = ref.result()
    assert result.returncode == 0, result.stderr[-3000:]
    return reference, killed, stopped, stopped_result


def test_joint_schedule_kill_and_resume_is_bitwise_equal(joint):
    reference, killed, _, _ = joint
    resumed = run(killed, "schedule=joint", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(reference, killed)


# ---------------------------------------------------------------------- pre-emption
def _wait(ready, proc: Launched) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not ready():
        assert proc.poll() is None, "the run ended too early"
        assert time.monotonic() < deadline
        time.sleep(0.005)


def _in_stage(run_dir: Path, stage: int):
    metrics = run_dir / "metrics.csv"
    return lambda: metrics.is_file() and f"train/stage_{stage}/" in metrics.read_text()


#: a signalled run ends at its next batch, after writing its checkpoint: seconds on an idle
#: machine; the bound leaves room for a 2-core machine that runs other trainings beside the test
#: (10 s was once missed by 0.8 s there)
STOP_WITHIN_S = 30


def _stop(proc: Launched, signum: int, seed: int) -> tuple[subprocess.CompletedProcess, float]:
    """Sends ``signum`` after a random delay; returns the finished process and how long it
    took to exit after the signal."""
    import random

    time.sleep(random.Random(seed).uniform(0.0, 0.25))
    sent = time.monotonic()
    proc.send_signal(signum)
    result = proc.result()
    return result, time.monotonic() - sent


@pytest.mark.parametrize("seed", [11])
def test_sigterm_mid_stage_checkpoints_and_resume_is_bitwise_equal(runs, seed):
    root, reference, _ = runs
    stopped = root / f"sigterm_{seed}"
    proc = spawn(stopped, "checkpoint_every=0")  # no periodic checkpoint: the signal's only
    _wait(_in_stage(stopped, 1), proc)
    result, seconds = _stop(proc, signal.SIGTERM, seed)
    assert result.returncode == 128 + signal.SIGTERM, (seed, result.stderr[-2000:])
    assert seconds < STOP_WITHIN_S
    assert "Traceback" not in result.stderr and "resume=true" in result.stderr
    status = json.loads((stopped / "status.json").read_text())
    assert status["status"] == "interrupted" and status["signal"] == "SIGTERM"
    written = list((stopped / "checkpoints").rglob("frames-*"))
    assert written or (stopped / "stage_0.pt").is_file(), "nothing saved"
    resumed = run(stopped, "checkpoint_every=0", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(reference, stopped)
    assert not (stopped / "status.json").exists()
    launches = json.loads((stopped / "eval.json").read_text())["training"]["launches"]
    assert [x["outcome"] for x in launches] == ["interrupted", "done"]


def test_sigint_ends_with_one_line_and_its_exit_code(tmp_path):
    proc = spawn(tmp_path / "run")
    _wait(_in_stage(tmp_path / "run", 1), proc)
    result, _ = _stop(proc, signal.SIGINT, 0)
    assert result.returncode == 128 + signal.SIGINT
    lines = [line for line in result.stderr.splitlines() if line.startswith("stages-train:")]
    assert len(lines) == 1 and "interrupted by SIGINT" in lines[0]
    assert "Traceback" not in result.stderr and "KeyboardInterrupt" not in result.stderr


def test_sigterm_during_the_joint_schedule_resumes_bitwise(joint):
    reference, _, stopped, (result, seconds) = joint
    assert result.returncode == 128 + signal.SIGTERM, result.stderr[-2000:]
    assert seconds < STOP_WITHIN_S and list((stopped / "checkpoints" / "joint").glob("frames-*"))
    resumed = run(stopped, "schedule=joint", "checkpoint_every=0", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(reference, stopped)


# ---------------------------------------------------------------------- one writer
def test_a_second_process_in_the_same_directory_exits_2_naming_the_first(tmp_path):
    # the first run cannot end on its own while the second starts (a slow machine may take
    # many seconds to import torch): a large budget with no early stop, stopped by SIGTERM
    endless = ["task.stages.s1.frames=100000000", "task.stages.s1.success_threshold=null"]
    first = spawn(tmp_path / "run", *endless)
    try:
        lock = tmp_path / "run" / ".stages" / "lock"
        _wait(lambda: lock.is_file() and lock.read_text().strip(), first)
        second = run(tmp_path / "run", "seed=1", *endless)
        assert first.poll() is None, "the first run ended before the second was refused"
        assert second.returncode == 2, second.stderr[-2000:]
        assert f"in use by another process (process {first.pid} on" in second.stderr
        first.send_signal(signal.SIGTERM)
        assert first.result().returncode == 128 + signal.SIGTERM
    finally:
        first.stop()
    assert OmegaConf.load(tmp_path / "run" / "config.yaml").seed == 0


# ---------------------------------------------------------------------- damaged checkpoints
@pytest.mark.parametrize("damage", ["truncated", "forged"])
def test_a_damaged_newest_checkpoint_falls_back_to_the_one_before(runs, damage):
    root, reference, killed = runs
    damaged = root / f"{damage}_checkpoint"
    shutil.copytree(killed, damaged)
    checkpoints = sorted((damaged / "checkpoints" / "stage_1").glob("frames-*"))
    assert len(checkpoints) >= 2
    buffer = next((checkpoints[-1] / "components").glob("*replay_buffer"))
    if damage == "truncated":  # its checksum tells
        storage = max(buffer.rglob("*.memmap"), key=lambda p: p.stat().st_size)
        storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
        why = storage.name
    else:  # checksummed anew: it only fails to load
        (buffer / "state.json").write_text('{"kind": "dict", "items": []}')
        write_checksums(buffer)
        why = "cannot be read back"
    result = run(damaged, "resume=true")
    assert result.returncode == 0, result.stderr[-3000:]
    logs = result.stdout + result.stderr
    assert "is damaged" in logs and why in logs
    assert logs.count(f"checkpoint {checkpoints[-1]} is damaged") == 1, logs  # said once
    assert f"resuming from the checkpoint before it: {checkpoints[-2]}" in logs
    assert_same_run(reference, damaged)


def test_every_checkpoint_damaged_exits_2_with_one_line(runs):
    root, _, killed = runs
    damaged = root / "all_damaged"
    shutil.copytree(killed, damaged)
    for ckpt in (damaged / "checkpoints" / "stage_1").glob("frames-*"):
        (ckpt / "manifest.json").write_text("{")
    result = run(damaged, "resume=true")
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("stages-train: ") and "manifest.json is damaged" in last
    assert "Fix: delete" in last and "Traceback" not in result.stderr


def test_resume_with_a_config_naming_other_code_is_refused(runs, tmp_path):
    root, reference, _ = runs
    tampered = root / "tampered"
    shutil.copytree(reference, tampered)
    marker = tmp_path / "ran"
    cfg = OmegaConf.load(tampered / "config.yaml")
    cfg.task.env.size = {"_target_": "os.makedirs", "name": str(marker)}
    OmegaConf.save(cfg, tampered / "config.yaml")
    result = run(tampered, "resume=true")
    assert result.returncode == 2 and "config.yaml is damaged" in result.stderr
    (tampered / ".stages" / "run.json").unlink()  # no checksum: the config itself is compared
    result = run(tampered, "resume=true")
    assert result.returncode == 2 and "task.env.size" in result.stderr
    assert not marker.exists()


# ---------------------------------------------------------------------- a file that cannot grow
@pytest.mark.parametrize("checkpoint_every", [0, 256])
def test_a_write_that_fails_names_the_file_leaves_no_temporary_and_resumes(
    runs, tmp_path, checkpoint_every
):
    _, reference, _ = runs
    run_dir = tmp_path / "run"
    extra = f"checkpoint_every={checkpoint_every}"
    argv = ["stages-train", *OVERRIDES, f"hydra.run.dir={run_dir}", extra]
    # a stage file (about 250 kB), or a checkpoint (the first, at 256 frames: its learner's
    # JSON part, about 35 kB; its replay storage holds only the transitions stored so far),
    # is larger than the limit; what a run writes before training is under 10 kB
    limit = 150_000 if checkpoint_every == 0 else 30_000
    result = Launched(argv, tmp_path, TIMEOUT_S, file_size_limit=limit).result()
    assert result.returncode == 2, result.stderr[-2000:]
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("stages-train: cannot write ") and "File too large" in last
    assert ("stage_1.pt" if checkpoint_every == 0 else "checkpoints") in last
    assert not [p for p in run_dir.rglob("*") if p.name.endswith(".tmp") or ".stage-" in p.name]
    assert json.loads((run_dir / "status.json").read_text())["status"] == "failed"
    resumed = run(run_dir, extra, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_run(reference, run_dir)


# ------------------------------------------------------------------ a gymnasium env of one's own
TESTS = Path(__file__).resolve().parent
#: ``tests/drift_env.py``: episodes of 200 steps whose resets and steps draw from np_random
DRIFT = [
    "task=gym",
    "task.env.env_id=drift_env:Drift-v0",
    "task.env.stage_fn._target_=drift_env.drift_stage",
    "experiment=smoke",
    *[
        f"all_stages.{key}={value}"
        for key, value in {
            "num_envs": 4,
            "frames": 1024,
            "frames_per_batch": 128,
            "init_random_frames": 128,
            "eval_every": 512,
            "eval_episodes": 8,
        }.items()
    ],
    "eval.episodes=8",
    "checkpoint_every=256",
    "eval.plots=false",
    "progress=false",
    f"device={os.environ.get('STAGES_TEST_DEVICE', 'cpu')}",
]


def spawn_drift(run_dir: Path, *extra: str) -> Launched:
    """``stages-train`` on ``Drift-v0``, ``tests/`` on the path (where its module is)."""
    path = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    argv = ["stages-train", *DRIFT, f"hydra.run.dir={run_dir}", *extra]
    return Launched(argv, run_dir.parent, TIMEOUT_S, PYTHONPATH=path)


@pytest.mark.parametrize("seeds", [[], ["seeds=[0,3]"]], ids=["one_seed", "stacked_seeds"])
def test_a_gymnasium_env_killed_mid_stage_then_resumed_is_bitwise_equal(tmp_path, seeds):
    """A gymnasium env of one's own, SIGKILLed in its first stage (its episodes 64 to 160 steps
    into their 200): the resumed run rebuilds the running episodes and ends as the
    uninterrupted one, the stage trained after the resume included. With ``seeds=[...]`` one
    checkpoint holds every seed's state, beside their directories, and is dropped once every
    stage is kept."""
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    ref = spawn_drift(reference, *seeds)
    proc = spawn_drift(killed, *seeds)
    checkpoints = killed / ("seed_checkpoints" if seeds else "checkpoints") / "stage_1"
    kill_when(proc, lambda: len(list(checkpoints.glob("frames-*"))) >= 2, delay=0.05)
    result = ref.result()
    assert result.returncode == 0, result.stderr[-3000:]
    run_dirs = ["seed_0", "seed_3"] if seeds else ["."]
    assert not any((killed / d / "stage_1.pt").exists() for d in run_dirs)  # killed mid-stage
    resumed = spawn_drift(killed, *seeds, "resume=true").result()
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    logs = resumed.stdout + resumed.stderr
    assert "resuming from" in logs and "did not rebuild" not in logs
    assert ("2 seeds: resuming from" in logs) == bool(seeds)
    for run_dir in run_dirs:
        assert_same_run(reference / run_dir, killed / run_dir)
    assert not checkpoints.parent.exists()  # dropped once every stage is kept


def test_a_gymnasium_env_that_draws_from_elsewhere_says_so_in_one_line_at_resume(tmp_path):
    """``Drift-v0`` stepping on a generator of its own: the resumed run says, once, that its
    episodes start over (not bitwise), and finishes."""
    entropy = "+task.env.entropy=true"
    killed = tmp_path / "killed"
    proc = spawn_drift(killed, entropy)
    checkpoints = killed / "checkpoints" / "stage_1"
    kill_when(proc, lambda: any(checkpoints.glob("frames-*")), delay=0.05)
    resumed = spawn_drift(killed, entropy, "resume=true").result()
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    lines = [
        line
        for line in (resumed.stdout + resumed.stderr).splitlines()
        if "did not rebuild its running episodes" in line
    ]
    assert len(lines) == 1, lines
    assert "'drift_env:Drift-v0'" in lines[0] and "they start over" in lines[0]
    assert (killed / "stage_0.pt").is_file() and (killed / "eval.json").is_file()
