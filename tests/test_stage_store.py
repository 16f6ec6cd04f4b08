"""Stages as reusable artifacts: their identity, the shared stage store (bitwise reuse,
concurrent jobs, damaged entries, ``stages-store``) and ``init_from``.

Every run is a three-stage 9 x 9 grid world whose stages train for 256 frames (about a second
each run): what is checked is which stages are trained and that reused ones are bit for bit
the ones training gives, not what they learned.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
import torch
from helpers import TINY_STAGE, Launched, console_script, hydra_config, run_cli

from torchrl_stages.cli import stage_store as stages_store_cli
from torchrl_stages.config import ConfigError
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.identity import stage_identities
from torchrl_stages.runs.stage_store import SharedStageStore, StoreError

THREE = [
    "task.env.size=9",
    "task.env.num_stages=3",
    "~task.stages.s3",
    "~task.stages.s4",
    *[f"task.stages.s{k}.{key}={value}" for k in range(3) for key, value in TINY_STAGE.items()],
    "eval.plots=false",
    "progress=false",
    "eval.episodes=8",
]


def compose(*overrides: str):
    with hydra_config(*THREE) as make:
        return make(*overrides)


def train(run_dir: Path, *overrides: str) -> dict:
    return Experiment(compose(*overrides), run_dir).run()[0]


def weights(run_dir: Path, stage: int) -> dict[str, torch.Tensor]:
    return torch.load(run_dir / f"stage_{stage}.pt", weights_only=True)["model"]


def same_stage(a: Path, b: Path, stage: int) -> bool:
    wa, wb = weights(a, stage), weights(b, stage)
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def evaluation(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in ("training",)}


# ---------------------------------------------------------------------- identity
def test_a_stage_identity_follows_its_config_and_the_later_stages_only():
    base = stage_identities(compose())
    assert len(set(base)) == 3
    s1 = stage_identities(compose("task.stages.s1.lr=2e-3"))
    assert s1[2] == base[2] and s1[1] != base[1] and s1[0] != base[0]
    s0 = stage_identities(compose("task.stages.s0.frames=512"))
    assert s0[1:] == base[1:] and s0[0] != base[0]
    assert all(a != b for a, b in zip(stage_identities(compose("seed=1")), base, strict=True))
    assert all(
        a != b
        for a, b in zip(stage_identities(compose("task.env.max_steps=50")), base, strict=True)
    )
    # a stage of a jointly trained run is never taken for a backward one
    assert all(
        a != b for a, b in zip(stage_identities(compose("schedule=joint")), base, strict=True)
    )
    probe = stage_identities(compose("eval.probe=true"))  # stage 0's evaluations run it
    assert probe[1:] == base[1:] and probe[0] != base[0]
    for unrelated in (
        "progress=true",
        "logger=none",
        "checkpoint_every=128",
        "eval.episodes=3",
        "eval.plots=true",
        "objective.metric=mean_steps",
        "stage_store=/tmp/elsewhere",
        "task.eval_episodes=7",
    ):
        assert stage_identities(compose(unrelated)) == base, unrelated


def test_reuse_is_refused_where_stages_train_together():
    for schedule in ("joint", "flat"):
        with pytest.raises(ConfigError, match="stage_store=.*schedule=backward"):
            Experiment(compose(f"schedule={schedule}", "stage_store=/tmp/x"), "/tmp/unused")


# ---------------------------------------------------------------------- the store
def test_stages_from_the_store_are_bitwise_those_training_gives(tmp_path):
    store = f"stage_store={tmp_path / 'store'}"
    plain = train(tmp_path / "plain")
    filling = train(tmp_path / "filling", store)
    assert filling["training"]["reused"] == {}
    reusing = train(tmp_path / "reusing", store)
    assert sorted(reusing["training"]["reused"]) == ["s0", "s1", "s2"]
    for k in range(3):
        assert same_stage(tmp_path / "plain", tmp_path / "reusing", k)
    assert evaluation(plain) == evaluation(filling) == evaluation(reusing)
    # stage 1 changed: stages 0 and 1 are trained, stage 2 is taken, and the run is the one
    # that trains everything
    changed = train(tmp_path / "changed", store, "task.stages.s1.lr=2e-3")
    assert list(changed["training"]["reused"]) == ["s2"]
    reference = train(tmp_path / "reference", "task.stages.s1.lr=2e-3")
    for k in range(3):
        assert same_stage(tmp_path / "changed", tmp_path / "reference", k)
    assert evaluation(changed) == evaluation(reference)
    assert len(SharedStageStore(tmp_path / "store").entries()) == 5


def test_a_damaged_entry_is_never_served(tmp_path, caplog):
    store = SharedStageStore(tmp_path / "store")
    train(tmp_path / "first", f"stage_store={store.root}")
    identities = stage_identities(compose())
    stage_file = store.path(identities[1]) / "stage.pt"
    data = bytearray(stage_file.read_bytes())
    data[len(data) // 2] ^= 0xFF
    stage_file.write_bytes(bytes(data))
    (store.path(identities[0]) / "sha256.json").unlink()
    with caplog.at_level("WARNING"):
        again = train(tmp_path / "again", f"stage_store={store.root}")
    assert list(again["training"]["reused"]) == ["s2"]  # s1 retrained, then s0 (depends on it)
    assert "is damaged" in caplog.text and identities[1] in caplog.text
    for k in range(3):
        assert same_stage(tmp_path / "first", tmp_path / "again", k)
    assert all(e.damaged is None for e in store.entries())  # replaced by the retrained ones


def test_a_foreign_or_linked_entry_is_damaged(tmp_path):
    store = SharedStageStore(tmp_path / "store")
    train(tmp_path / "first", f"stage_store={store.root}")
    ids = stage_identities(compose())
    # an entry copied under another identity
    (store.root / "entries" / ids[2]).rename(store.root / "entries" / ("f" * 32))
    (store.root / "entries" / ids[2]).symlink_to(store.root / "entries" / ("f" * 32))
    assert store.get(ids[2]) is None  # a link: removed, not served
    assert store.get("f" * 32) is None  # holds another identity
    assert {e.identity for e in store.entries()} == {ids[0], ids[1]}


def test_jobs_that_need_the_same_stage_train_it_once(tmp_path):
    store = tmp_path / "store"
    overrides = [*THREE, f"stage_store={store}", "threads=1"]
    procs = [
        Launched(["stages-train", *overrides, f"hydra.run.dir={tmp_path / name}"], tmp_path)
        for name in ("a", "b")
    ]
    results = [p.result() for p in procs]
    for result in results:
        assert result.returncode == 0, result.stderr[-2000:]
    reused = [
        json.loads((tmp_path / n / "eval.json").read_text())["training"]["reused"]
        for n in ("a", "b")
    ]
    for name in ("s0", "s1", "s2"):  # each stage trained by exactly one of the two jobs
        assert (name in reused[0]) != (name in reused[1]), reused
    for k in range(3):
        assert same_stage(tmp_path / "a", tmp_path / "b", k)
    assert len(SharedStageStore(store).entries()) == 3
    assert "reused stages" in "".join(r.stdout + r.stderr for r in results)


def test_stages_store_lists_removes_and_prunes(tmp_path, capsys):
    store = SharedStageStore(tmp_path / "store")
    train(tmp_path / "run", f"stage_store={store.root}")
    ids = stage_identities(compose())
    stages_store_cli(["ls", str(store.root)])
    out = capsys.readouterr().out
    assert all(i[:12] in out for i in ids) and "3 entries" in out and "gridworld" in out
    stages_store_cli(["rm", str(store.root), ids[0][:10]])
    assert "removed" in capsys.readouterr().out
    assert not list((store.root / "locks").iterdir())  # released and removed by the trainer
    assert {e.identity for e in store.entries()} == set(ids[1:])
    (store.path(ids[1]) / "entry.json").write_text("{}")  # damaged
    (store.root / "tmp" / f"{ids[2]}.999999999-deadbeef").mkdir()  # a killed writer's leftover
    stages_store_cli(["prune", str(store.root), "--dry-run"])
    assert "would remove 2 item(s)" in capsys.readouterr().out
    stages_store_cli(["prune", str(store.root)])
    assert [e.identity for e in store.entries()] == [ids[2]]
    assert not list((store.root / "tmp").iterdir())
    old = time.time() - 3 * 86400
    os.utime(store.path(ids[2]) / "entry.json", (old, old))
    stages_store_cli(["prune", str(store.root), "--older-than", "2d"])
    assert store.entries() == []
    with pytest.raises(SystemExit):
        stages_store_cli(["rm", str(store.root), "abc"])
    assert "no entry with an identity starting 'abc'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        stages_store_cli(["ls", str(tmp_path)])
    assert "is not a stage store" in capsys.readouterr().err


def test_a_store_that_cannot_be_created_fails_before_training(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(StoreError, match=r"stage_store=.*cannot create it.*Fix"):
        Experiment(compose(f"stage_store={blocker / 'store'}"), tmp_path / "run")
    assert not list((tmp_path / "run").glob("*"))  # nothing written


# ---------------------------------------------------------------------- init_from
def test_init_from_takes_the_unchanged_later_stages(tmp_path):
    train(tmp_path / "first")
    second = train(tmp_path / "second", f"init_from={tmp_path / 'first'}", "task.stages.s1.lr=2e-3")
    assert list(second["training"]["reused"]) == ["s2"]
    assert second["training"]["reused"]["s2"] == f"init_from {tmp_path / 'first'}"
    reference = train(tmp_path / "reference", "task.stages.s1.lr=2e-3")
    for k in range(3):
        assert same_stage(tmp_path / "second", tmp_path / "reference", k)
    assert evaluation(second) == evaluation(reference)
    # a change of stage 0 only: both later stages are taken
    third = train(tmp_path / "third", f"init_from={tmp_path / 'first'}", "task.stages.s0.lr=2e-3")
    assert sorted(third["training"]["reused"]) == ["s1", "s2"]


def test_init_from_errors_name_the_fix(tmp_path):
    with pytest.raises(StoreError, match=r"init_from=.*no run there.*Fix"):
        Experiment(compose(f"init_from={tmp_path / 'nothing'}"), tmp_path / "run")
    train(tmp_path / "run")
    with pytest.raises(StoreError, match="this run's own directory"):
        Experiment(compose(f"init_from={tmp_path / 'run'}", "resume=true"), tmp_path / "run")


@pytest.mark.e2e
def test_stages_train_prints_the_reused_stages(tmp_path):
    first = run_cli(
        [console_script("stages-train"), *THREE, f"hydra.run.dir={tmp_path / 'a'}"], tmp_path
    )
    assert first.returncode == 0, first.stderr[-2000:]
    second = run_cli(
        [
            console_script("stages-train"),
            *THREE,
            "task.stages.s0.lr=2e-3",
            f"init_from={tmp_path / 'a'}",
            f"hydra.run.dir={tmp_path / 'b'}",
        ],
        tmp_path,
    )
    assert second.returncode == 0, second.stderr[-2000:]
    text = second.stdout + second.stderr
    assert "stage 2 (s2): reused from init_from" in text
    assert "reused stages: s1, s2; trained: s0" in text
    bad = run_cli(
        [
            console_script("stages-train"),
            *THREE,
            "init_from=/nonexistent/run",
            f"hydra.run.dir={tmp_path / 'c'}",
        ],
        tmp_path,
    )
    assert bad.returncode == 2 and "init_from=/nonexistent/run: no run there" in bad.stderr
