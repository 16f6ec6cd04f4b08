"""Loggers: torchrl's, plus one tidy ``metrics.csv`` per run whichever backend is chosen.

``metrics.csv`` (``name,step,value``) is the run directory's own record of every scalar: the
learning curves (``learning_curves.png``) and sweep summaries read it. The ``csv`` backend writes
it next to torchrl's per-tag files; every other backend (``tensorboard``, ``wandb``, ``mlflow``)
and ``none`` get it through :class:`RunLogger`.

Both loggers take ``observers`` (:data:`Observer`): code that watches a run's metrics as they
are written (``stages-tune`` reports each stage evaluation to its Optuna trial) and may end the
run by raising :class:`StopRun`. The training loops only log; they never know who watches.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from torch import Tensor
from torchrl.record.loggers import CSVLogger, Logger, get_logger

METRICS_HEADER = ["name", "step", "value"]

#: ``observer(metrics, step)``: sees each group of scalars logged together (one stage
#: evaluation's numbers, one batch's losses; :class:`~torchrl_stages.loop.MetricsLog`), once
#: they are written to ``metrics.csv``; it may end the run by raising :class:`StopRun`
Observer = Callable[[dict[str, float], int], None]


class StopRun(Exception):  # noqa: N818 - an outcome, not an error
    """Raised by an :data:`Observer` to end a run early, as ``status`` (e.g. ``pruned``): the
    run's ``status.json`` records the status and the reason
    (:meth:`torchrl_stages.runs.experiment.Experiment.run`).

    Examples:
        >>> err = StopRun("pruned", "stage 4's success rate 0.1 is below the median")
        >>> err.status, str(err)
        ('pruned', "stage 4's success rate 0.1 is below the median")
    """

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status = status


class _Observed:
    """What both loggers share: the observers and :meth:`notify`."""

    observers: tuple[Observer, ...] = ()

    def notify(self, metrics: dict[str, float], step: int) -> None:
        """Shows a group of scalars just logged (at ``step``) to every observer."""
        for observer in self.observers:
            observer(metrics, step)


class MetricsCSVLogger(_Observed, CSVLogger):
    """torchrl's ``CSVLogger`` that also appends every scalar to one ``name,step,value`` file.

    Names carry the namespace (``train/stage_3/loss``, ``eval/stage_3/success_rate``,
    ``eval/final/success_rate``); ``step`` counts the frames of that stage.

    Examples:
        >>> import tempfile, pathlib
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> logger = MetricsCSVLogger("csv", log_dir=str(d), metrics_file=d / "metrics.csv")
        >>> logger.log_scalar("train/stage_0/loss", 0.5, step=10)
        >>> (d / "metrics.csv").read_text().splitlines()
        ['name,step,value', 'train/stage_0/loss,10,0.5']
    """

    def __init__(
        self,
        exp_name: str,
        log_dir: str,
        metrics_file: str | Path,
        observers: Sequence[Observer] = (),
    ) -> None:
        super().__init__(exp_name=exp_name, log_dir=log_dir)
        self.metrics_file = Path(metrics_file)
        self.observers = tuple(observers)
        if not self.metrics_file.exists():
            self._append(["name", "step", "value"])

    def _append(self, row: list) -> None:
        # Open per row: nothing stays open, and a crashed run keeps every row written so far.
        with self.metrics_file.open("a", newline="") as f:
            csv.writer(f).writerow(row)

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        super().log_scalar(name, value, step=step)
        self._append([name, step, float(value)])

    def _files(self) -> dict[str, Path]:
        """The files this logger appends to, by path relative to the run directory."""
        root = self.metrics_file.parent
        files = [self.metrics_file, *sorted(Path(self.experiment.log_dir).rglob("*.csv"))]
        return {f.relative_to(root).as_posix(): f for f in files}

    def position(self) -> dict[str, int]:
        """The size of every file this logger appends to (``metrics.csv`` and torchrl's
        per-tag files), for :meth:`rewind`."""
        return {name: f.stat().st_size for name, f in self._files().items() if f.is_file()}

    def rewind(self, position: dict[str, int]) -> None:
        """Truncates the files to a :meth:`position` (rows written after it are dropped; files
        created after it are emptied), so a resumed run does not log anything twice."""
        for name, f in self._files().items():
            if f.is_file():
                with f.open("r+b") as handle:
                    handle.truncate(position.get(name, 0))
        if self.metrics_file.stat().st_size == 0:
            self._append(["name", "step", "value"])


class RunLogger(_Observed, Logger):
    """Appends every scalar to the run's ``metrics.csv`` and forwards every call to a torchrl
    ``backend`` logger (``None``: no backend, ``logger=none``).

    Like :class:`MetricsCSVLogger` it has :meth:`position` / :meth:`rewind` for resumed runs
    (on ``metrics.csv``; a backend's own records are not rewound).

    Examples:
        >>> import tempfile, pathlib
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> logger = RunLogger(d / "metrics.csv")
        >>> logger.log_scalar("eval/stage_1/success_rate", 1.0, step=512)
        >>> (d / "metrics.csv").read_text().splitlines()
        ['name,step,value', 'eval/stage_1/success_rate,512,1.0']
    """

    def __init__(
        self,
        metrics_file: str | Path,
        backend: Logger | None = None,
        observers: Sequence[Observer] = (),
    ) -> None:
        self.backend = backend
        self.observers = tuple(observers)
        self.metrics_file = Path(metrics_file)
        self.metrics_file.parent.mkdir(parents=True, exist_ok=True)
        if not self.metrics_file.exists() or self.metrics_file.stat().st_size == 0:
            self._append(METRICS_HEADER)
        name = backend.exp_name if backend is not None else "metrics"
        super().__init__(exp_name=name, log_dir=str(self.metrics_file.parent))

    def _create_experiment(self) -> Any:
        return None if self.backend is None else self.backend.experiment

    def _append(self, row: list) -> None:
        with self.metrics_file.open("a", newline="") as f:  # nothing stays open
            csv.writer(f).writerow(row)

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        self._append([name, step, float(value)])
        if self.backend is not None:
            self.backend.log_scalar(name, value, step=step)

    def log_video(self, name: str, video: Tensor, step: int | None = None, **kwargs) -> None:
        if self.backend is not None:
            self.backend.log_video(name, video, step=step, **kwargs)

    def log_hparams(self, cfg: DictConfig | dict) -> None:
        if self.backend is not None:
            self.backend.log_hparams(cfg)

    def log_histogram(self, name: str, data: Sequence, **kwargs) -> None:
        if self.backend is not None:
            self.backend.log_histogram(name, data, **kwargs)

    def __repr__(self) -> str:
        return f"RunLogger({self.metrics_file}, backend={self.backend!r})"

    def position(self) -> dict[str, int]:
        """The size of ``metrics.csv``, for :meth:`rewind`."""
        return {self.metrics_file.name: self.metrics_file.stat().st_size}

    def rewind(self, position: dict[str, int]) -> None:
        """Truncates ``metrics.csv`` to a :meth:`position` (a resumed run logs nothing twice)."""
        with self.metrics_file.open("r+b") as handle:
            handle.truncate(position.get(self.metrics_file.name, 0))
        if self.metrics_file.stat().st_size == 0:
            self._append(METRICS_HEADER)


def make_logger(cfg: DictConfig, run_dir: Path, observers: Sequence[Observer] = ()) -> Logger:
    """The logger of ``cfg.logger`` writing inside ``run_dir``; every backend (``none``
    included) also writes the run's ``metrics.csv``, and shows what it logs to ``observers``."""
    backend = cfg.logger.backend
    metrics_file = run_dir / "metrics.csv"
    if backend == "none":
        return RunLogger(metrics_file, observers=observers)
    if backend == "csv":
        return MetricsCSVLogger(
            "csv", log_dir=str(run_dir), metrics_file=metrics_file, observers=observers
        )
    kwargs = {}
    if backend == "wandb":
        kwargs = {"project": cfg.logger.project}
    external = get_logger(
        backend, logger_name=str(run_dir), experiment_name=cfg.logger.exp_name, wandb_kwargs=kwargs
    )
    return RunLogger(metrics_file, external, observers=observers)
