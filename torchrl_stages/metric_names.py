"""The names a run's metrics are logged under, ``<kind>/<scope>[_<index>]/<metric>``: written
by :func:`metric_name`, read back by :func:`parse_metric`."""

from __future__ import annotations

import re
from dataclasses import dataclass

#: the scope of a stage's own learner (a schedule's phases log under a scope of their own)
STAGE = "stage"
#: the whole-run scopes: the whole task followed during training, and evaluated at the end
TASK, FINAL = "task", "final"

_NAME = re.compile(
    r"^(?P<kind>train|eval)/(?P<scope>[a-z]+)(?:_(?P<index>\d+))?/(?P<metric>[^/].*)$"
)


@dataclass(frozen=True)
class MetricName:
    """A metric's name read back."""

    kind: str  # train | eval
    scope: str  # stage | joint | task | final | a schedule's own loops
    index: int | None  # the stage (or phase) of a loop's scope; None for whole-run scopes
    metric: str


def metric_name(kind: str, scope: str, index: int | None, metric: str) -> str:
    """The name a metric is logged under (``index``: ``None`` for a whole-run scope)."""
    where = scope if index is None else f"{scope}_{index}"
    return f"{kind}/{where}/{metric}"


def parse_metric(name: str) -> MetricName | None:
    """``name`` read back (``None``: not of this scheme).

    Examples:
        >>> parse_metric(metric_name("train", "phase", 1, "loss"))
        MetricName(kind='train', scope='phase', index=1, metric='loss')
        >>> parse_metric(metric_name("eval", TASK, None, "success_rate")).index, parse_metric("x")
        (None, None)
    """
    match = _NAME.match(name)
    if match is None:
        return None
    index = None if match["index"] is None else int(match["index"])
    return MetricName(match["kind"], match["scope"], index, match["metric"])


def is_loop_evaluation(name: str, metric: str = "success_rate") -> bool:
    """Whether ``name`` is ``metric`` of a loop's (indexed) evaluation: what a tuner prunes on."""
    parsed = parse_metric(name)
    if parsed is None or parsed.index is None:
        return False
    return parsed.kind == "eval" and parsed.metric == metric
