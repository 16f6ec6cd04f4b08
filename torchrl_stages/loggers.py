"""A run's logger: every scalar to the run's ``metrics.csv`` (read by the learning curves and
sweep summaries) and to the torchrl backend ``logger.backend`` names."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from torch import Tensor
from torchrl.record.loggers import CSVLogger, Logger, get_logger

from torchrl_stages.integrity import DamagedFileError

METRICS_HEADER = ["name", "step", "value"]

#: ``observer(metrics, step)`` sees each group of scalars logged together, once written; it
#: may end the run by raising :class:`StopRun`
Observer = Callable[[dict[str, float], int], None]


class StopRun(Exception):  # noqa: N818 - an outcome, not an error
    """Raised by an :data:`Observer` to end a run early; ``status.json`` records both strings.

    Examples:
        >>> err = StopRun("pruned", "below the median")
        >>> err.status, str(err)
        ('pruned', 'below the median')
    """

    def __init__(self, status: str, reason: str) -> None:
        super().__init__(reason)
        self.status = status


class RunLogger(Logger):
    """Appends every scalar to ``metrics_file`` and forwards every call to a torchrl
    ``backend`` (``None``: none); :meth:`rewind` lets a resumed run log nothing twice.

    Examples:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
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

    def _append(self, row: list) -> None:  # opened per row: a crashed run keeps every row
        with self.metrics_file.open("a", newline="") as f:
            csv.writer(f).writerow(row)

    def notify(self, metrics: dict[str, float], step: int) -> None:
        for observer in self.observers:
            observer(metrics, step)

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

    def _files(self) -> dict[str, Path]:
        """The files this logger appends to, by path relative to the run directory."""
        root, files = self.metrics_file.parent, [self.metrics_file]
        if isinstance(self.backend, CSVLogger):
            files += sorted(Path(self.backend.experiment.log_dir).rglob("*.csv"))
        return {f.relative_to(root).as_posix(): f for f in files if f.is_file()}

    def position(self) -> dict[str, int]:
        """The size of every file this logger appends to, for :meth:`rewind`."""
        return {name: f.stat().st_size for name, f in self._files().items()}

    def rewind(self, position: dict[str, int]) -> None:
        """Truncates the files to a :meth:`position` (files made after it are emptied);
        :class:`DamagedFileError` for one shorter than it was there (rows were lost)."""
        files = self._files()
        for name, f in files.items():
            size, written = f.stat().st_size, position.get(name, 0)
            if size < written:
                raise DamagedFileError(
                    f,
                    f"{size} bytes, where the run had written {written} by the point it resumes "
                    "from: rows were lost. Fix: restore it from a copy of the run, or retrain "
                    "with overwrite=true",
                )
        for name, f in files.items():
            with f.open("r+b") as handle:
                handle.truncate(position.get(name, 0))
        if self.metrics_file.stat().st_size == 0:
            self._append(METRICS_HEADER)


def make_logger(cfg: DictConfig, run_dir: Path, observers: Sequence[Observer] = ()) -> Logger:
    """The :class:`RunLogger` of ``cfg.logger`` in ``run_dir``."""
    backend, external = cfg.logger.backend, None
    if backend == "csv":
        external = CSVLogger("csv", log_dir=str(run_dir))
    elif backend != "none":
        kwargs = {"project": cfg.logger.project} if backend == "wandb" else {}
        external = get_logger(backend, str(run_dir), cfg.logger.exp_name, wandb_kwargs=kwargs)
    return RunLogger(run_dir / "metrics.csv", external, observers=observers)
