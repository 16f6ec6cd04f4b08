"""Sweep summaries: ``torchrl_stages.sweeps`` on hand-made job directories (in-process), and the
Hydra callback and ``stages-report`` on real sweeps (the console script, tiny ``experiment=smoke``).

The two ``stages-train -m`` commands start together when the module's first test runs (two
cores) and each test waits only for the one it reads.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import Launched, assert_figure
from scipy.stats import trim_mean

from torchrl_stages.cli import report
from torchrl_stages.sweeps import aggregate_jobs, find_jobs, read_job, summarize_sweep
from torchrl_stages.sweeps.stats import _mean_and_iqm, performance_profiles

TIMEOUT_S = 300


# ------------------------------------------------------------------ hand-made sweeps
def make_job(
    root: Path,
    name: str,
    overrides: list[str],
    success: float | None = None,
    status: tuple[str, str] | None = None,
    curve: list[tuple[int, float]] = (),
    value_error: float | None = None,
) -> Path:
    job = root / name
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    if success is not None:
        result = {
            "success_rate": success,
            "mean_return": success * 2,
            "mean_steps": 10.0 + success,
            "training": {"seconds": 1.5, "stages": [{"frames": 256, "updates": 4}] * 2},
        }
        if value_error is not None:  # a task's headline metric, and one it does not headline
            result["task_metrics"] = {"value_map_max_abs_error": value_error, "other": 3.0}
            result["headline_metrics"] = ["value_map_max_abs_error"]
        (job / "eval.json").write_text(json.dumps(result))
    if status is not None:
        (job / "status.json").write_text(json.dumps({"status": status[0], "reason": status[1]}))
    rows = ["name,step,value"] + [f"eval/stage_0/success_rate,{s},{v}" for s, v in curve]
    rows += [f"train/stage_0/loss,{s},0.5" for s, _ in curve]
    (job / "metrics.csv").write_text("\n".join(rows) + "\n")
    return job


@pytest.fixture
def sweep(tmp_path) -> Path:
    """Two configurations (lr) x three seeds, one failed and one unfinished job, and a nested
    job directory (as with hydra.sweep.subdir=${hydra.job.override_dirname})."""
    root = tmp_path / "sweep"
    n = 0
    for lr, successes in (("1e-3", [1.0, 0.5, 0.75]), ("1e-2", [0.0, 0.25, None])):
        for seed, success in enumerate(successes):
            overrides = [f"task.stages.s0.lr={lr}", f"seed={seed}"]
            curve = [(128, 0.0), (256, success or 0.0)] if seed != 1 else [(128, 0.5)]
            if success is None:
                make_job(root, str(n), overrides, status=("diverged", "stage 0 diverged: nan"))
            else:
                make_job(root, str(n), overrides, success, curve=curve, value_error=0.1 * seed)
            n += 1
    make_job(root, "10", ["task.stages.s0.lr=1e-3", "seed=9"])  # killed: nothing written
    make_job(root, "nested/lr=1e-3,seed=3", ["task.stages.s0.lr=1e-3", "seed=3"], 1.0)
    (root / "multirun.yaml").write_text("hydra: {}\n")
    (root / ".submitit").mkdir()  # launcher files are not jobs
    (root / ".submitit" / "x").mkdir()
    (root / ".submitit" / "x" / "status.json").write_text("{}")
    return root


def _jobs(values, config="lr=1"):
    from torchrl_stages.sweeps import Job

    return [
        Job(Path(str(k)), str(k), [config, f"seed={k}"], k, "done", metrics={"success_rate": v})
        for k, v in enumerate(values)
    ]


def test_mean_iqm_and_their_bootstrap_intervals():
    values = np.random.default_rng(0).normal(1.0, 0.1, size=50)
    agg = aggregate_jobs(_jobs(values))[0]  # success_rate first
    assert agg.mean == pytest.approx(values.mean()) and agg.n == 50
    assert agg.iqm == pytest.approx(trim_mean(values, 0.25))  # the middle half
    assert agg.ci_low < agg.mean < agg.ci_high and agg.ci_high - agg.ci_low < 0.1
    assert agg.iqm_low < agg.iqm < agg.iqm_high
    assert aggregate_jobs(_jobs(values), seed=3) == aggregate_jobs(_jobs(values), seed=3)
    assert aggregate_jobs(_jobs(values), seed=3) != aggregate_jobs(_jobs(values), seed=4)
    outlier = aggregate_jobs(_jobs([-100.0, 1.0, 2.0, 100.0]))[0]
    assert outlier.iqm == 1.5 and outlier.mean == 0.75
    single = aggregate_jobs(_jobs([2.0]))[0]
    assert (single.mean, single.ci_low, single.ci_high) == (2.0, 2.0, 2.0)


def test_performance_profile_is_the_fraction_of_runs_above_each_threshold():
    jobs = _jobs([0.0, 0.5, 1.0, 1.0]) + _jobs([0.25], config="lr=2")
    profiles = performance_profiles(jobs, np.array([-0.1, 0.0, 0.5, 0.99, 1.0]))
    profile, interval = profiles["lr=1"]
    assert profile.tolist() == [1.0, 0.75, 0.5, 0.5, 0.0]
    assert interval.shape == (2, 5) and np.all(interval[0] <= profile + 1e-12)
    assert np.all(profile <= interval[1] + 1e-12)
    assert profiles["lr=2"][0].tolist() == [1.0, 1.0, 0.0, 0.0, 0.0]


def test_the_bootstrapped_statistics_are_rliables():
    # the summary computes rliable's mean, IQM and score distribution its own faster way; the
    # bootstrap intervals come from the same resamples either way
    from rliable import library as rly
    from rliable import metrics as rlm

    from torchrl_stages.sweeps.stats import interval_estimates

    rng = np.random.default_rng(0)
    taus = np.linspace(-0.1, 1.1, 13)
    for n in (1, 2, 3, 4, 5, 7, 20, 101):
        scores = rng.random((n, 1)).round(2)  # ties, as success rates have
        ours = _mean_and_iqm(scores)
        assert ours[0] == pytest.approx(rlm.aggregate_mean(scores), rel=1e-12)
        assert ours[1] == pytest.approx(rlm.aggregate_iqm(scores), rel=1e-12)
        profile = performance_profiles(_jobs(scores.ravel().tolist()), taus)["lr=1"]
        assert profile[0].tolist() == rly.score_distributions(scores, taus).tolist()
    scores = rng.random((9, 1))
    reference = interval_estimates(
        scores, lambda s: np.array([rlm.aggregate_mean(s), rlm.aggregate_iqm(s)]), seed=2
    )
    ours = interval_estimates(scores, _mean_and_iqm, seed=2)
    for a, b in zip(ours, reference, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12)


def test_find_jobs_any_depth_in_natural_order(sweep):
    names = [p.relative_to(sweep).as_posix() for p in find_jobs(sweep)]
    assert names == ["0", "1", "2", "3", "4", "5", "10", "nested/lr=1e-3,seed=3"]
    single = find_jobs(sweep / "0")  # a run directory on its own is one job
    assert single == [sweep / "0"]


def test_read_job_status_and_numbers(sweep):
    done, failed, killed = (read_job(sweep / n, sweep) for n in ("0", "5", "10"))
    assert (done.status, done.seed, done.config) == ("done", 0, "task.stages.s0.lr=1e-3")
    assert done.metrics["success_rate"] == 1.0 and done.frames == 512 and done.updates == 8
    assert done.train_seconds == 1.5 and done.metrics["value_map_max_abs_error"] == 0.0
    assert "other" not in done.metrics  # only the metrics the task names as its headline
    assert failed.status == "diverged" and failed.reason == "stage 0 diverged: nan"
    assert killed.status == "incomplete" and "still running" in killed.reason


def test_a_job_on_its_own_and_labels_without_shared_overrides(tmp_path):
    from torchrl_stages.sweeps.figures import short_labels

    trial = make_job(tmp_path, "3", [], status=("pruned", "pruned at stage evaluation 2"))
    job = read_job(trial)  # named after its own folder
    assert (job.name, job.status, job.reason) == ("3", "pruned", "pruned at stage evaluation 2")
    labels = short_labels(["a=1 seed=0", "a=2 seed=0"])
    assert labels == {"a=1 seed=0": "a=1", "a=2 seed=0": "a=2"}


def _aggregate(summary, config: str, metric: str = "success_rate"):
    (agg,) = [a for a in summary.aggregates if (a.config, a.metric) == (config, metric)]
    return agg


def test_summary_files(sweep):
    summary = summarize_sweep(sweep)
    assert set(summary.files) == {
        "summary.csv",
        "summary_configs.csv",
        "summary.md",
        "summary_curves.png",
        "summary_final.png",
        "summary_profile.png",
    }
    with (sweep / "summary.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["job"] for r in rows] == ["0", "1", "2", "3", "4", "5", "10", "nested/lr=1e-3,seed=3"]
    assert [r["status"] for r in rows] == ["done"] * 5 + ["diverged", "incomplete", "done"]
    assert rows[5]["reason"] == "stage 0 diverged: nan" and rows[5]["success_rate"] == ""
    assert rows[0]["overrides"] == "task.stages.s0.lr=1e-3 seed=0"
    assert rows[0]["config"] == "task.stages.s0.lr=1e-3" and rows[0]["seed"] == "0"
    assert float(rows[1]["value_map_max_abs_error"]) == pytest.approx(0.1)
    assert "other" not in rows[0]
    assert rows[0]["frames"] == "512" and rows[0]["train_seconds"] == "1.5"
    # per configuration, across seeds: the finished ones
    good = _aggregate(summary, "task.stages.s0.lr=1e-3")
    assert (good.n, good.failed) == (4, 1)  # seeds 0, 1, 2, 3 finished; seed 9 did not
    assert good.mean == pytest.approx(np.mean([1.0, 0.5, 0.75, 1.0]))
    assert good.iqm == pytest.approx(trim_mean([1.0, 0.5, 0.75, 1.0], 0.25))
    assert good.ci_low <= good.mean <= good.ci_high
    bad = _aggregate(summary, "task.stages.s0.lr=1e-2", "mean_steps")
    assert (bad.n, bad.failed, bad.mean) == (2, 1, pytest.approx(10.125))
    md = (sweep / "summary.md").read_text()
    assert "| task.stages.s0.lr=1e-2 | success_rate | 2 | 1 |" in md
    assert "stage 0 diverged: nan" in md and "![summary_curves.png]" in md
    for png in ("summary_curves.png", "summary_final.png", "summary_profile.png"):
        assert_figure(sweep / png)


def test_summary_is_reproducible(sweep):
    summarize_sweep(sweep)
    first = {n: (sweep / n).read_bytes() for n in ("summary.csv", "summary_configs.csv")}
    summarize_sweep(sweep)
    assert first == {n: (sweep / n).read_bytes() for n in first}


def test_summary_without_finished_jobs(tmp_path):
    make_job(tmp_path, "0", ["seed=0"], status=("invalid", "invalid config: gamma"))
    summary = summarize_sweep(tmp_path)
    assert [j.status for j in summary.jobs] == ["invalid"]
    assert not {"summary_final.png", "summary_curves.png", "summary_profile.png"} & set(
        summary.files
    )
    assert _aggregate(summary, "(defaults)").mean is None


def test_a_job_whose_files_are_not_utf8_is_summarized_without_them(tmp_path, capsys):
    job = make_job(tmp_path, "0", ["seed=0"], success=1.0, curve=[(128, 1.0)])
    for name in (".hydra/overrides.yaml", "metrics.csv", "status.json"):
        (job / name).write_bytes(b"- lr=\xff\xfe\n\0\0")
    report([str(tmp_path)])
    assert "(defaults): success 1.000" in capsys.readouterr().out


def test_report_rejects_a_directory_without_jobs(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        report([str(tmp_path)])
    assert info.value.code == 2
    assert "no job directory" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        report([str(tmp_path / "missing")])


# ------------------------------------------------------------------ real sweeps
SWEEPS = {
    # the shortest real sweep, the sweeps guide's (its page's block is run here, not twice)
    "smoke": ["-m", "experiment=smoke", "seed=0,1"],
    # every job refused by validation: the summary is written although the sweep fails
    "invalid": ["-m", "experiment=smoke", "task.stages.s0.gamma=1.5,2.0", "eval.plots=false"],
}


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweeps")
    launched = {
        name: Launched(["stages-train", *args, f"hydra.sweep.dir={root / name}"], root, TIMEOUT_S)
        for name, args in SWEEPS.items()
    }

    def result(name: str) -> tuple[int, str, Path]:
        done = launched[name].result()
        return done.returncode, done.stdout + done.stderr, root / name

    yield result
    for command in launched.values():
        command.stop()


@pytest.mark.e2e
@pytest.mark.slow
def test_smoke_sweep_writes_its_summary(sweeps):
    guide = (Path(__file__).parents[1] / "docs" / "guides" / "sweeps.md").read_text()
    assert "stages-train -m experiment=smoke seed=0,1 hydra.sweep.dir=sweeps/smoke" in guide
    assert "stages-report sweeps/smoke " in guide  # test_stages_report_reproduces_the_summary
    code, output, sweep_dir = sweeps("smoke")
    assert code == 0, output[-4000:]
    assert f"Sweep summary: {sweep_dir / 'summary.md'} (2 of 2 jobs finished)" in output
    with (sweep_dir / "summary.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2
    assert [(r["seed"], r["status"], r["config"]) for r in rows] == [
        ("0", "done", "experiment=smoke"),
        ("1", "done", "experiment=smoke"),
    ]
    for row in rows:
        assert 0.0 <= float(row["success_rate"]) <= 1.0
        # the grid world's headline metric: its value-map error
        assert float(row["value_map_max_abs_error"]) >= 0.0
        assert int(row["frames"]) == 5 * 1024 and float(row["train_seconds"]) > 0
    for png in ("summary_curves.png", "summary_final.png", "summary_profile.png"):
        assert_figure(sweep_dir / png)
    assert "experiment=smoke" in (sweep_dir / "summary.md").read_text()


@pytest.mark.e2e
@pytest.mark.slow
def test_stages_report_reproduces_the_summary(sweeps, tmp_path, capsys):
    code, output, sweep_dir = sweeps("smoke")
    assert code == 0, output[-4000:]
    names = ("summary.csv", "summary_configs.csv", "summary.md")
    written = {n: (sweep_dir / n).read_bytes() for n in names}
    pngs = ("summary_curves.png", "summary_final.png", "summary_profile.png")
    figures = {n: (sweep_dir / n).read_bytes() for n in pngs}
    for name in (*written, *figures):
        (sweep_dir / name).unlink()
    report([str(sweep_dir)])
    assert "experiment=smoke: success" in capsys.readouterr().out
    assert {n: (sweep_dir / n).read_bytes() for n in names} == written
    assert {n: (sweep_dir / n).read_bytes() for n in figures} == figures


@pytest.mark.e2e
@pytest.mark.slow
def test_failed_sweep_still_writes_its_summary(sweeps):
    code, output, sweep_dir = sweeps("invalid")
    assert code != 0  # the sweep says that its jobs failed
    with (sweep_dir / "summary.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["status"] for r in rows] == ["invalid", "invalid"]
    assert "task.stages.s0.gamma=1.5: must be in (0, 1]" in rows[0]["reason"]
    assert "Sweep summary:" in output


def test_performance_profile_legend_stays_inside_the_figure(tmp_path, monkeypatch):
    """Long labels (a sweep over many overrides) wrap: the legend sits below the plot, inside
    the figure, and hides no curve."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from torchrl_stages.sweeps import figures

    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, out: drawn.append(fig) or out)
    long = " ".join(
        f"task.stages.s{k}.lr=0.000{k + 1} task.stages.s{k}.gamma=0.9" for k in range(5)
    )
    jobs = _jobs([0.2, 0.9, 1.0], config=f"{long} seed_group=a")
    jobs += _jobs([0.5, 0.6], config="task.stages.s0.lr=0.01 seed_group=b")
    figures.plot_performance_profile(jobs, tmp_path / "profile.png")
    (fig,) = drawn
    canvas = FigureCanvasAgg(fig)
    canvas.draw()  # the layout, as savefig makes it
    renderer = canvas.get_renderer()
    (legend,) = fig.legends
    box, page = legend.get_window_extent(renderer), fig.bbox
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1
    assert not box.overlaps(fig.axes[0].get_window_extent(renderer))
    assert len(legend.get_texts()) == 2
    fig.savefig(tmp_path / "profile.png")
    assert_figure(tmp_path / "profile.png")
