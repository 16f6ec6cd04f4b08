"""Tests for the Fig. 2 style plots: each writes a PNG without touching the pyplot backend."""

import subprocess
import sys

import numpy as np
import pytest

from torchrl_stages.envs.cargo.figures import plot_cargo_figure
from torchrl_stages.envs.gridworld.figures import plot_grid_trajectories, plot_value_map
from torchrl_stages.plots import plot_learning_curves

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SIZE, WIDTH, TARGET = 25, 5, (24, 24)


def assert_png(path, expected):
    assert path == expected
    data = path.read_bytes()
    assert len(data) > 1000
    assert data[:8] == PNG_MAGIC


def straight_path(row):
    """Right along ``row`` to the last column, then down to the target."""
    return [(row, c) for c in range(SIZE)] + [(r, SIZE - 1) for r in range(row + 1, SIZE)]


def test_trajectories_png(tmp_path):
    out = tmp_path / "fig" / "traj.png"
    paths = [straight_path(0), straight_path(12), [(20, 3)]]
    got = plot_grid_trajectories(
        paths,
        size=SIZE,
        stage_width=WIDTH,
        target=TARGET,
        out=out,
        title="greedy",
        labels=["a", "b", "c"],
    )
    assert_png(got, out)


def test_trajectories_without_labels_accepts_str_path(tmp_path):
    out = tmp_path / "traj.png"
    got = plot_grid_trajectories(
        [straight_path(5), []], size=SIZE, stage_width=WIDTH, target=TARGET, out=str(out)
    )
    assert_png(got, out)


def test_trajectories_label_count_mismatch(tmp_path):
    with pytest.raises(ValueError):
        plot_grid_trajectories(
            [straight_path(0)],
            size=SIZE,
            stage_width=WIDTH,
            target=TARGET,
            out=tmp_path / "x.png",
            labels=["a", "b"],
        )


def test_value_map_png(tmp_path):
    values = np.random.default_rng(0).normal(size=(SIZE, SIZE))
    values[3, 3] = np.nan  # unvisited cells are left blank
    out = tmp_path / "values.png"
    got = plot_value_map(values, stage_width=WIDTH, target=TARGET, out=out, title="V")
    assert_png(got, out)
    got = plot_value_map(values, stage_width=WIDTH, out=tmp_path / "plain.png")
    assert_png(got, tmp_path / "plain.png")


def test_value_map_rejects_1d(tmp_path):
    with pytest.raises(ValueError):
        plot_value_map(np.zeros(SIZE), stage_width=WIDTH, out=tmp_path / "bad.png")


def test_learning_curves_png(tmp_path):
    csv_path = tmp_path / "metrics.csv"
    lines = ["name,step,value"]
    for stage in range(3):
        for step in range(0, 500, 100):
            lines.append(f"train/stage_{stage}/episode_return,{step},{-step / 100 + stage}")
            lines.append(f"train/stage_{stage}/loss,{step},{1 / (step + 1)}")
        lines.append(f"eval/stage_{stage}/success_rate,400,0.9")
    lines.append("eval/task/success_rate,0,1.0")
    lines.append("train/stage_0/updates,100,7")
    csv_path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "curves.png"
    got = plot_learning_curves(csv_path, out)
    assert_png(got, out)


# what each learner logs per collected batch (torchrl_stages/learners/*.py) and evaluation
LOGGED = {
    "dqn": ["loss", "grad_norm"],
    "ddpg": ["loss_actor", "loss_value", "grad_norm_actor", "grad_norm_critic"],
    "td3": ["loss_qvalue", "grad_norm_critic", "loss_actor", "grad_norm_actor"],
}
TRAIN_EXTRA = ["episode_return", "episode_success", "updates"]
EVAL = ["success_rate", "value_error", "mean_return", "mean_steps", "discounted_return"]


def test_learning_curves_show_every_loss_and_the_evaluations(tmp_path):
    from torchrl_stages.plots import _stage_panels, read_stage_metrics

    csv_path = tmp_path / "metrics.csv"
    lines = ["name,step,value"]
    for stage, algo in enumerate(LOGGED):
        for step in (256, 512, 768):
            for key in LOGGED[algo] + TRAIN_EXTRA:
                lines.append(f"train/stage_{stage}/{key},{step},{0.1 + step / 1000}")
            for key in EVAL:
                lines.append(f"eval/stage_{stage}/{key},{step},0.5")
    lines.append("eval/joint_1/success_rate,512,0.25")  # a joint-schedule phase evaluation
    csv_path.write_text("\n".join(lines) + "\n")
    stages = read_stage_metrics(csv_path)
    titles = {k: [title for title, _ in _stage_panels(stages[k])] for k in stages}
    common = [
        "gradient norm",
        "evaluation success rate",
        "evaluation value error |V(s0) - G|",
        "training episode return",
    ]
    assert titles[0] == ["loss", *common]
    assert titles[1] == ["loss_value", "loss_actor", *common]
    assert titles[2] == ["loss_qvalue", "loss_actor", *common]
    success = dict(_stage_panels(stages[1]))["evaluation success rate"]
    assert ("eval", "joint", "success_rate") in success  # the phase evaluation joins row 1
    for panels in titles.values():
        assert not any("episode_success" in t or "updates" in t for t in panels)
    out = plot_learning_curves(csv_path, tmp_path / "curves.png")
    assert_png(out, tmp_path / "curves.png")
    from helpers import assert_figure

    assert_figure(out)


def test_learning_curves_empty(tmp_path):
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("name,step,value\n")
    out = tmp_path / "curves.png"
    assert plot_learning_curves(csv_path, out) is None
    assert not out.exists()


def test_learning_curves_only_unmatched_rows(tmp_path):
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("name,step,value\neval/task/success_rate,0,1.0\n")
    assert plot_learning_curves(csv_path, tmp_path / "c.png") is None


@pytest.mark.parametrize(
    "robots, stages",
    [(("slider", "propelled"), [0, 0, 1, 1, 0, 1]), (("propelled",), [0] * 6)],
)
def test_cargo_figure_png(tmp_path, robots, stages):
    occupancy = np.zeros((50, 70), dtype=bool)
    occupancy[10:20, 40:46] = True
    # segments are drawn in runs per stage; non-contiguous runs of one stage are split
    path = [[30.0, 10.0], [33.0, 10.0], [36.0, 11.0], [40.0, 25.0], [34.5, 25.0], [36.0, 26.0]]
    out = tmp_path / "cargo.png"
    got = plot_cargo_figure(
        occupancy,
        [(path, stages), ([[5.0, 5.0]], [0])],
        robots=robots,
        stage_line=35.0,
        target=(62.0, 36.0),
        success_radius=2.0,
        out=out,
    )
    assert_png(got, out)


def test_module_does_not_load_pyplot():
    """Plotting must not import pyplot (which would pick or switch the user's backend)."""
    import torchrl_stages.plots as plots

    code = (
        "import importlib.util, sys\n"
        f"spec = importlib.util.spec_from_file_location('plots', {plots.__file__!r})\n"
        "spec.loader.exec_module(importlib.util.module_from_spec(spec))\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
