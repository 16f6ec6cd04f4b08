"""The benchmark scripts on tiny budgets (the headline ones through ``regenerate.py --quick``):
each writes the rows and the table the docs include."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import helpers
import pytest
from helpers import TINY_STAGE, assert_figure
from omegaconf import OmegaConf

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
TINY = {**TINY_STAGE, "eval_every": 0}  # no stage evaluations: what is compared is reuse
MISSING = "the minigrid extra is not installed: pip install '.[minigrid]'"
try:
    import minigrid  # noqa: F401
except ImportError:
    minigrid = None


def run_script(name: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return helpers.run_script(SCRIPTS / name, *args, cwd=SCRIPTS, timeout=timeout)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """``regenerate.py --quick``: every headline benchmark script once, on tiny budgets."""
    out = tmp_path_factory.mktemp("quick")
    docs = SCRIPTS.parent / "docs"
    tables = sorted([*(docs / "tables").glob("*.md"), *docs.glob("*.png")])
    before = {path: path.read_bytes() for path in tables}
    done = run_script("regenerate.py", "--quick", "--out", str(out), timeout=1200)  # ~4 min
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert {path: path.read_bytes() for path in tables} == before  # the docs' copies untouched
    return out


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.skipif(minigrid is None, reason=MISSING)
def test_regenerate_runs_every_headline_benchmark(quick, tmp_path):
    """The full mode replays each headline table's own commands into docs/tables/ (the
    schedules' figures into docs/); the quick mode runs each script once on tiny budgets and
    leaves the docs' tables alone."""
    listed = run_script("regenerate.py", "--list", "--out", str(tmp_path))
    assert listed.returncode == 0, listed.stderr[-3000:]
    *shown, figure = listed.stdout.splitlines()
    assert len(shown) > 14 and all("--table ../docs/tables/" in line for line in shown)
    assert figure.startswith("minigrid_schedules.png: figure_minigrid.py --out ")
    assert any("--seeds 10 11 12 13 14 15 16 17 18 19" in line for line in shown)
    ran = sorted(p.parent.name for p in quick.glob("*/table.md"))
    assert ran == [
        "cargo_sdql_and_single_robots",
        "gridworld_seeds_0_9",
        "manipulator_ddpg_seeds_0_7",
        "minigrid_keycorridor_s3r2_settings",
        "schedules_gridworld",
        "seeds_wallclock_four_ways",
        "waypoints_gym_env",
    ]
    assert_figure(quick / "minigrid_schedules.png")  # the README's figure, of the quick run
    # the schedules' figure: success (and the merged value error) against frames
    assert_figure(quick / "schedules_gridworld" / "schedules_gridworld-homo.png")
    assert any("--figures ../docs" in line for line in shown if "schedules_cargo" in line)
    for table in quick.glob("*/table.md"):
        text = table.read_text()
        assert "experiment=" in text and str(quick) not in text, table  # portable commands
    # the bring-your-own-env guide's commands: the template's stages, one per env stage
    gym = quick / "waypoints_gym_env"
    rows = json.loads((gym / "rows.json").read_text())
    assert [r["variant"] for r in rows] == ["discrete/dqn", "box/sac"]
    assert all(len(r["stage_frames"]) == 3 for r in rows)  # the env's three stages
    box = OmegaConf.load(gym / "box_sac_seed0" / "config.yaml").task.stages
    assert [box[s].algo for s in ("s0", "s1", "s2")] == ["sac"] * 3  # the template's algo


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.skipif(minigrid is None, reason=MISSING)
def test_benchmark_gym_vector_compares_the_three_ways(tmp_path):
    args = ["--envs", "2", "--steps", "5", "--repeats", "1", "--out", str(tmp_path)]
    done = run_script("benchmark_gym_vector.py", *args)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["env"] for r in rows] == ["CartPole-v1", "MiniGrid-DoorKey-8x8-v0"]
    assert all(set(r["fps"]) == {"serial", "sync", "async"} for r in rows)
    assert "sync / serial" in (tmp_path / "table.md").read_text()


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.skipif(minigrid is None, reason=MISSING)
def test_benchmark_minigrid_writes_its_table_and_its_failures(quick, tmp_path):
    out_dir = quick / "minigrid_keycorridor_s3r2_settings"
    level = "MiniGrid-KeyCorridorS3R2-v0"
    rows = json.loads((out_dir / "rows.json").read_text())
    assert [(r["level"], r["schedule"]) for r in rows] == [(level, "backward")]
    assert len(rows[0]["stage_frames"]) == 3 and rows[0]["episodes"] == 32
    assert (out_dir / f"minigrid_{level}_backward_seed0.png").is_file()
    assert f"{level} backward: success mean" in (out_dir / "table.md").read_text()
    # where its greedy stage policy fails: the loop each failed start ends in
    run_dir = out_dir / f"{level}_backward_seed0"
    out = tmp_path / "failures"
    args = ["--stage", "2", "--starts", "4", "--steps", "12", "--out", str(out), str(run_dir)]
    done = run_script("minigrid_greedy_failures.py", *args)
    assert done.returncode == 0, done.stderr[-3000:]
    row = (out / "table.md").read_text().splitlines()[-1].split(" | ")
    assert row[0] == f"| {run_dir.name}" and row[2] == "2"
    assert row[1] == "view_doors=True, gamma=0.95, advantage_learning=0.9"  # the family's
    loops = row[4].removesuffix(" |")
    failed = 0 if loops == "-" else sum(int(p.rsplit(" ", 1)[1]) for p in loops.split("; "))
    assert row[3].endswith("/4") and int(row[3].split("/")[0]) + failed == 4
    # two launches' runs of one level, schedule and seed: named by their launch too
    again = tmp_path / "again" / run_dir.name
    shutil.copytree(run_dir, again)
    done = run_script("minigrid_greedy_failures.py", *args[:-1], str(run_dir), str(again))
    assert done.returncode == 0, done.stderr[-3000:]
    names = [r.split(" | ")[0] for r in (out / "table.md").read_text().splitlines()[-2:]]
    assert names == [f"| {out_dir.name}/{run_dir.name}", f"| again/{run_dir.name}"]


def test_a_failed_greedy_episode_is_classified_by_its_loop(monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPTS))
    from minigrid_greedy_failures import loop_kind

    assert loop_kind(["pickup"] * 8) == "repeats pickup"
    assert loop_kind(["right", "left"] * 4) == "alternates left, right"
    assert loop_kind(["left", "left", "right", "right"]) == "other"
    assert loop_kind(["forward", "left", "forward", "right"]) == "other"


def test_minigrid_rows_from_launches_apart_make_one_table(tmp_path, monkeypatch):
    """Rows accumulate in rows.json (a re-run replaces its row) and the table lists them all."""
    monkeypatch.syspath_prepend(str(SCRIPTS))
    import benchmark_minigrid as bench

    def row(seed, success, command):
        return {
            "level": "L",
            "schedule": "backward",
            "seed": seed,
            "success": success,
            "frames": 10,
            "seconds": 1.0,
            "machine_speed": 5e5,
            "command": command,
            "jobs": 2,
        }

    rows_file = tmp_path / "rows.json"
    bench.merge_rows(rows_file, [row(1, 0.5, "first")])
    bench.merge_rows(rows_file, [row(0, 0.9, "second")])
    rows = bench.merge_rows(rows_file, [row(1, 1.0, "third")])  # seed 1 again: replaced
    assert [(r["seed"], r["success"]) for r in rows] == [(0, 0.9), (1, 1.0)]
    text = bench.write_table(rows, tmp_path / "docs" / "minigrid.md")
    assert "$ second" in text and "$ third" in text and "$ first" not in text
    assert "L backward: success mean 95.0% (lowest 90.0%), 1/2 seeds at >= 95%" in text
    assert (tmp_path / "docs" / "minigrid.md").read_text() == text + "\n"


@pytest.mark.e2e
@pytest.mark.slow
def test_benchmark_stage_store_compares_the_sweeps_job_by_job(tmp_path):
    tiny = [f"task.stages.s{k}.{key}={v}" for k in range(5) for key, v in TINY.items()]
    done = run_script(
        "benchmark_stage_store.py",
        "--presets",
        "homo",
        "--lrs",
        "1e-3",
        "2e-3",
        "--out",
        str(tmp_path),
        *tiny,
        "eval.plots=false",
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["lr"] for r in rows] == ["1e-3", "2e-3"]
    assert all(r["bitwise"] for r in rows)
    assert rows[0]["store"]["reused"] == []
    assert all(r["store"]["reused"] == ["s1", "s2", "s3", "s4"] for r in rows[1:])
    table = (tmp_path / "table.md").read_text()
    assert "faster" in table and "machine speed" in table


@pytest.mark.e2e
@pytest.mark.slow
def test_benchmark_handoff_writes_the_table_and_figures(tmp_path):
    done = run_script(
        "benchmark_handoff.py",
        "--variants",
        "gridworld_missed",
        "--out",
        str(tmp_path),
        "experiment=smoke",
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["variant"] for r in rows] == ["gridworld_missed"]
    assert [h["boundary"] for h in rows[0]["handoff"]] == [f"s{k} -> s{k + 1}" for k in range(4)]
    table = (tmp_path / "table.md").read_text()
    assert "outside starts" in table and "machine speed" in table


@pytest.mark.skipif(minigrid is None, reason=MISSING)
def test_minigrid_random_walks_writes_its_table(tmp_path):
    done = run_script(
        "minigrid_random_walks.py",
        "--levels",
        "MiniGrid-DoorKey-5x5-v0",
        "--walks",
        "20",
        "--steps",
        "64",
        "--out",
        str(tmp_path),
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert [r["stage"] for r in rows] == [0, 1]
    assert all(0 <= r["all"] <= 20 and 0 <= r["family"] <= 20 for r in rows)
    assert "the family's actions" in (tmp_path / "table.md").read_text()
