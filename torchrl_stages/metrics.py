"""A run's metrics as its loops log them, one :class:`MetricsLog` per seed."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger

from torchrl_stages.evaluate import ended_well

__all__ = ["MetricsLog"]


class MetricsLog:
    """Scalars to a torchrl ``logger`` (none: dropped); its position and rewind where it has
    them, so that a resumed loop drops the rows of an interrupted attempt.

    Examples:
        >>> log = MetricsLog(None)
        >>> log({"train/stage_0/loss": 0.5}, step=128)
        >>> log.position()
        {}
    """

    def __init__(self, logger: Logger | None) -> None:
        self.logger = logger

    def __call__(self, metrics: dict[str, float | None], step: int) -> None:
        if self.logger is None:
            return
        logged = {key: value for key, value in metrics.items() if value is not None}
        for key, value in logged.items():
            self.logger.log_scalar(key, value, step=step)
        getattr(self.logger, "notify", lambda logged, step: None)(logged, step)

    def position(self) -> dict[str, int]:
        return getattr(self.logger, "position", dict)()

    def rewind(self, position: dict[str, int]) -> None:
        getattr(self.logger, "rewind", lambda position: None)(position)

    @staticmethod
    def episodes_by_row(batch: TensorDictBase) -> list[dict[str, float]]:
        """``episode_return`` and ``episode_success`` of the episodes each row (seed) of a
        ``[rows, ...]`` batch ended.

        Examples:
            >>> from tensordict import TensorDict
            >>> done = torch.tensor([[True, False], [False, False]]).unsqueeze(-1)
            >>> batch = TensorDict({"next": {"done": done, "terminated": done,
            ...     "episode_reward": torch.tensor([[[2.0], [5.0]], [[1.0], [1.0]]])}}, [2, 2])
            >>> MetricsLog.episodes_by_row(batch)
            [{'episode_return': 2.0, 'episode_success': 1.0}, {}]
        """
        rows = batch.shape[0]
        done = batch["next", "done"].reshape(rows, -1)
        ended = done.to(torch.float64)
        returns = batch["next", "episode_reward"].reshape(rows, -1).to(torch.float64) * ended
        success = (ended_well(batch).reshape(rows, -1) & done).to(torch.float64)
        counts, totals, wins = torch.stack([ended.sum(1), returns.sum(1), success.sum(1)]).tolist()
        return [
            {"episode_return": total / count, "episode_success": win / count} if count else {}
            for count, total, win in zip(counts, totals, wins, strict=True)
        ]
