"""Loggers: torchrl's, plus one tidy ``metrics.csv`` per run for the CSV backend."""

from __future__ import annotations

import csv
from pathlib import Path

from omegaconf import DictConfig
from torchrl.record.loggers import CSVLogger, Logger, get_logger


class MetricsCSVLogger(CSVLogger):
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

    def __init__(self, exp_name: str, log_dir: str, metrics_file: str | Path) -> None:
        super().__init__(exp_name=exp_name, log_dir=log_dir)
        self.metrics_file = Path(metrics_file)
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


def make_logger(cfg: DictConfig, run_dir: Path) -> Logger | None:
    """The logger of ``cfg.logger`` writing inside ``run_dir`` (``None`` for backend ``none``)."""
    backend = cfg.logger.backend
    if backend == "none":
        return None
    if backend == "csv":
        return MetricsCSVLogger("csv", log_dir=str(run_dir), metrics_file=run_dir / "metrics.csv")
    kwargs = {}
    if backend == "wandb":
        kwargs = {"project": cfg.logger.project}
    return get_logger(
        backend, logger_name=str(run_dir), experiment_name=cfg.logger.exp_name, wandb_kwargs=kwargs
    )
