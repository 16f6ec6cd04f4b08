"""Every logger backend keeps the run's ``metrics.csv``, so ``learning_curves.png`` (and sweep
summaries) exist whichever backend is chosen."""

from __future__ import annotations

import csv
import re
import tomllib
from pathlib import Path

from helpers import assert_figure
from torchrl.record.loggers import Logger

from torchrl_stages import Experiment
from torchrl_stages.config.checks import LOGGER_PACKAGES
from torchrl_stages.config.schema import LOGGER_BACKENDS
from torchrl_stages.loggers import RunLogger

ROOT = Path(__file__).resolve().parents[1]

TWO_STAGES = [
    "task.env.size=10",
    "task.env.num_stages=2",
    *[f"~task.stages.s{k}" for k in (2, 3, 4)],
]


class Recorder(Logger):
    """A stand-in for a tensorboard / wandb / mlflow logger: keeps what it is given."""

    def __init__(self) -> None:
        self.scalars: list[tuple[str, float, int | None]] = []
        super().__init__(exp_name="recorder", log_dir="unused")

    def _create_experiment(self):
        return "experiment"

    def log_scalar(self, name, value, step=None):
        self.scalars.append((name, value, step))

    def log_video(self, name, video, step=None, **kwargs):
        pass

    def log_hparams(self, cfg):
        self.scalars.append(("hparams", len(cfg), None))

    def log_histogram(self, name, data, **kwargs):
        pass

    def __repr__(self) -> str:
        return "Recorder()"


def test_run_logger_writes_metrics_and_forwards(tmp_path):
    backend = Recorder()
    logger = RunLogger(tmp_path / "metrics.csv", backend)
    assert logger.experiment == "experiment"
    logger.log_scalar("train/stage_1/loss", 0.5, step=256)
    position = logger.position()
    logger.log_scalar("train/stage_1/loss", 0.25, step=512)
    logger.log_hparams({"lr": 1e-3})
    assert backend.scalars == [
        ("train/stage_1/loss", 0.5, 256),
        ("train/stage_1/loss", 0.25, 512),
        ("hparams", 1, None),
    ]
    logger.rewind(position)  # a resumed run drops what came after the position
    with (tmp_path / "metrics.csv").open(newline="") as handle:
        assert list(csv.reader(handle)) == [
            ["name", "step", "value"],
            ["train/stage_1/loss", "256", "0.5"],
        ]


def test_learning_curves_without_a_metrics_backend(compose_cfg, tmp_path):
    cfg = compose_cfg("experiment=smoke", "logger=none", "eval.episodes=4", *TWO_STAGES)
    Experiment(cfg, tmp_path).run()
    with (tmp_path / "metrics.csv").open(newline="") as handle:
        names = {row["name"] for row in csv.DictReader(handle)}
    assert {"train/stage_0/loss", "train/stage_1/grad_norm", "eval/stage_0/value_error"} <= names
    assert not (tmp_path / "csv").exists()  # no torchrl CSV files: no backend
    assert_figure(tmp_path / "learning_curves.png")


def test_every_metrics_backend_has_an_extra_and_a_line_in_the_readme():
    """``pip install "torchrl-stages[<backend>]"`` installs the package that ``logger=<backend>``
    needs, and the README names every backend and those extras."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]
    for backend, package in LOGGER_PACKAGES.items():
        names = [re.match(r"[A-Za-z0-9_.-]+", r)[0].lower() for r in extras.get(backend, [])]
        assert names == [package], f"the extra [{backend}] should install {package}: {names}"
    readme = (ROOT / "README.md").read_text()
    listed = [set(m.split("|")) for m in re.findall(r"logger=([a-z]+(?:\|[a-z]+)+)", readme)]
    assert set(LOGGER_BACKENDS) in listed, listed
    assert 'pip install "torchrl-stages[tensorboard]"' in readme
