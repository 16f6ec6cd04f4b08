"""The Hydra callbacks of ``stages-train`` (``hydra.callbacks`` in ``conf/config.yaml``)."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from torchrl_stages.config import ConfigError
from torchrl_stages.config.checks import validate_sweeper
from torchrl_stages.failures import EXIT_INVALID
from torchrl_stages.sweeps import summarize_or_say


class RunDirCallback(Callback):
    """Notes which directories of ``hydra.run.dir`` Hydra is about to make, so that a refused
    run takes away what Hydra made and nothing else.

    Examples:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> root = Path(tempfile.mkdtemp())
        >>> run_dir = root / "outputs" / "run"
        >>> RunDirCallback().on_run_start(OmegaConf.create({"hydra": {"run": {"dir": run_dir}}}))
        >>> run_dir.mkdir(parents=True)  # what Hydra does next
        >>> RunDirCallback.remove_made(run_dir)
        >>> list(root.iterdir())  # outputs/ went with it
        []
    """

    run_dir: Path | None = None
    made: list[Path] = []  # the new directories of its path, deepest first
    held: frozenset[str] = frozenset()  # what it held before the launch

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        cls = RunDirCallback
        cls.run_dir, cls.made, cls.held = None, [], frozenset()
        with contextlib.suppress(Exception):  # a path it cannot tell: nothing is removed
            path = cls.run_dir = Path(os.path.abspath(str(config.hydra.run.dir)))
            while not path.exists() and path != path.parent:
                cls.made.append(path)
                path = path.parent
            if not cls.made:
                cls.held = frozenset(os.listdir(cls.run_dir))

    @classmethod
    def remove_made(cls, run_dir: Path) -> None:
        """Removes the Hydra log this launch made in ``run_dir``, then its new empty directories."""
        if cls.run_dir != Path(os.path.abspath(run_dir)):  # None: nothing noted
            return
        root = logging.getLogger()
        for handler in list(root.handlers):
            log = Path(getattr(handler, "baseFilename", ""))
            if log.parent == cls.run_dir and log.name not in cls.held:
                root.removeHandler(handler)
                handler.close()
                log.unlink(missing_ok=True)
        for path in cls.made:
            try:
                path.rmdir()
            except OSError:  # it holds something else
                break


class SweepSummaryCallback(Callback):
    """Checks the sweeper before any job runs, and writes the sweep's summary into
    ``hydra.sweep.dir`` when the multirun ends, also when a job failed.

    Examples:
        >>> import tempfile
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"hydra": {"sweep": {"dir": tempfile.mkdtemp()}}})
        >>> SweepSummaryCallback(plots=False).on_multirun_end(cfg)  # no job: nothing written
    """

    def __init__(self, plots: bool = True) -> None:
        self.plots = plots
        self._sweep_dir: Path | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            validate_sweeper(config.hydra.get("sweeper"), config)
        except ConfigError as err:
            print(f"stages-train: invalid config: {err}", file=sys.stderr)
            sys.exit(EXIT_INVALID)
        self._sweep_dir = Path(str(config.hydra.sweep.dir))
        # a failed job makes Hydra's sweepers raise before on_multirun_end: summarize at exit
        atexit.register(self._summarize)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        atexit.unregister(self._summarize)
        self._summarize()

    def _summarize(self) -> None:
        sweep_dir, self._sweep_dir = self._sweep_dir, None
        if sweep_dir is None:
            return
        summary = summarize_or_say(sweep_dir, self.plots, "stages-train: no sweep summary")
        if summary is not None:
            done = sum(job.status == "done" for job in summary.jobs)
            md, total = summary.files["summary.md"], len(summary.jobs)
            print(f"Sweep summary: {md} ({done} of {total} jobs finished)")
