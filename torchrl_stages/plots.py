"""A run's learning curves, and what the tasks' figures share (drawn on a matplotlib ``Figure``,
never pyplot: the user's backend is left alone)."""

from __future__ import annotations

import contextlib
import csv
import io
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from torchrl_stages.metric_names import parse_metric

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn: it costs every CLI start
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle


def save_figure(fig: Figure, out: str | Path) -> Path:
    """Writes ``fig`` as PNG to ``out``, making its parent folders."""
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, format="png")
    return path


#: losses in the order their panels appear (others follow, sorted)
_LOSS_ORDER = ("loss", "loss_value", "loss_qvalue", "loss_actor")
Series = dict[tuple[str, str, str], list[tuple[float, float]]]  # (kind, scope, metric) -> points


def read_metrics(metrics_csv: str | Path) -> dict[str, list[tuple[float, float]]]:
    """A ``metrics.csv``'s points (step, value) by metric name, rows without numbers (or
    damaged: bytes that are not UTF-8, NULs) left out."""
    out: dict[str, list[tuple[float, float]]] = defaultdict(list)
    text = Path(metrics_csv).read_text(errors="replace").replace("\0", "")
    for row in csv.DictReader(io.StringIO(text, newline="")):
        with contextlib.suppress(KeyError, TypeError, ValueError):
            out[row.get("name") or ""].append((float(row["step"]), float(row["value"])))
    return out


def read_stage_metrics(metrics_csv: str | Path) -> dict[int, Series]:
    """A ``metrics.csv``'s rows of each stage (or joint phase: ``eval/joint_1/...``) by index."""
    out: dict[int, Series] = defaultdict(lambda: defaultdict(list))
    for name, points in read_metrics(metrics_csv).items():
        parsed = parse_metric(name)
        if parsed is not None and parsed.index is not None:
            out[parsed.index][(parsed.kind, parsed.scope, parsed.metric)] = points
    return out


def _stage_panels(series: Series) -> list[tuple[str, list]]:
    """One stage's panels: each loss, the gradient norms, evaluations and episode return."""

    def pick(kind: str, test) -> list[tuple[str, str, str]]:
        return sorted(k for k in series if k[0] == kind and test(k[2]))

    losses = sorted(
        {k[2] for k in pick("train", lambda m: m.startswith("loss"))},
        key=lambda m: (_LOSS_ORDER.index(m) if m in _LOSS_ORDER else len(_LOSS_ORDER), m),
    )
    panels = [(loss, pick("train", lambda m, loss=loss: m == loss)) for loss in losses]
    panels += [
        ("gradient norm", pick("train", lambda m: m.startswith("grad_norm"))),
        ("evaluation success rate", pick("eval", lambda m: m == "success_rate")),
        ("evaluation value error |V(s0) - G|", pick("eval", lambda m: m == "value_error")),
        ("training episode return", pick("train", lambda m: m == "episode_return")),
    ]
    return [(title, keys) for title, keys in panels if keys]


def plot_learning_curves(metrics_csv: str | Path, out: str | Path) -> Path | None:
    """One row of panels per stage of a ``metrics.csv`` against the stage's frames, a joint
    phase's evaluations dashed in its stage's row."""
    stages = read_stage_metrics(metrics_csv)
    rows = [(k, panels) for k in sorted(stages) if (panels := _stage_panels(stages[k]))]
    if not rows:
        return None
    ncols = max(len(panels) for _, panels in rows)
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    width, height = 3.6 * ncols, 2.7 * len(rows) + 0.4  # a panel with its labels: 3.6 x 2.7 in
    fig = Figure(figsize=(width, height))
    # fixed margins in inches: tight_layout draws the figure once more (a third of its cost)
    pad = {"left": 0.75 / width, "right": 1 - 0.15 / width, "wspace": 0.45, "hspace": 0.55}
    fig.subplots_adjust(bottom=0.5 / height, top=1 - 0.3 / height, **pad)
    for r, (stage, panels) in enumerate(rows):
        series = stages[stage]
        for c, (title, keys) in enumerate(panels):
            ax = fig.add_subplot(len(rows), ncols, r * ncols + c + 1)
            for i, (kind, scope, metric) in enumerate(keys):
                steps, vals = zip(*sorted(series[kind, scope, metric]), strict=True)
                label = metric if scope == "stage" else f"{metric} (joint phase {stage})"
                style = "-" if scope == "stage" else "--"
                marker = "o" if len(steps) == 1 or kind == "eval" else None
                ax.plot(steps, vals, ls=style, marker=marker, ms=3, color=f"C{i % 10}", label=label)
            values = [v for key in keys for _, v in series[key]]
            if title == "evaluation success rate":
                ax.set_ylim(-0.05, 1.05)
            elif min(values) > 0 and max(values) > 20 * min(values):  # spans decades
                ax.set_yscale("log")
            ax.set_title(f"stage {stage}: {title}", fontsize=9)
            ax.set_xlabel("frames in stage", fontsize=8)
            ax.xaxis.set_major_locator(MaxNLocator(4))  # frame counts: few, readable ticks
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            if len(keys) > 1 or keys[0][1] != "stage":
                ax.legend(fontsize=7)
    return save_figure(fig, out)


def circle(center: Sequence[float], radius: float, color: str, style: str) -> Circle:
    """An unfilled circle patch."""
    from matplotlib.patches import Circle

    return Circle(tuple(center), radius, fill=False, color=color, linestyle=style)
