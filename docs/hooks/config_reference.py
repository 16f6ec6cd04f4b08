"""MkDocs hook: the configuration reference, generated from the config dataclasses.

``reference/config.md`` holds the marker ``<!-- config-reference -->``; this hook replaces it
with one table per dataclass (the root config, its blocks, the stage keys every algorithm
shares, then each registered algorithm's and schedule's own keys): key, type, default and the
comment written beside the field in the source.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing

MARKER = "<!-- config-reference -->"


def _comments(cls: type) -> dict[str, str]:
    """Each field's comment in ``cls``'s source: the ``#`` lines just above it, then the one
    beside it."""
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):
        return {}
    found, above = {}, []
    for line in lines:
        text = line.strip()
        if text.startswith("#"):
            above.append(text.lstrip("# "))
            continue
        match = re.match(r"^(\w+)\s*:[^#]*?(?:#\s*(.*))?$", text)
        if match and not text.startswith(("def ", "class ", "@")):
            found[match.group(1)] = " ".join([*above, match.group(2) or ""]).strip()
        above = []
    return found


def _default(field: dataclasses.Field) -> str:
    if field.default is not dataclasses.MISSING:
        value = field.default
    elif field.default_factory is not dataclasses.MISSING:
        value = field.default_factory()
        if dataclasses.is_dataclass(value):
            return "(block)"
    else:
        return "required"
    text = repr(value)
    if text.startswith("'${") or text.startswith("'???"):
        text = text.strip("'")
    return text


def _type(field: dataclasses.Field, hints: dict) -> str:
    hint = hints.get(field.name, field.type)
    text = getattr(hint, "__name__", None) if not typing.get_args(hint) else None
    return text or str(hint).replace("typing.", "")


def table(cls: type, own_only: bool = False) -> str:
    """A Markdown table of ``cls``'s fields (``own_only``: those its bases do not have)."""
    hints = typing.get_type_hints(cls)
    inherited = set()
    if own_only:
        for base in cls.__mro__[1:]:
            if dataclasses.is_dataclass(base):
                inherited |= {f.name for f in dataclasses.fields(base)}
    comments = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            comments.update(_comments(klass))
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for field in dataclasses.fields(cls):
        if field.name in inherited:
            continue
        meaning = comments.get(field.name, "").replace("|", "\\|")
        default = _default(field).replace("|", "\\|")
        rows.append(f"| `{field.name}` | `{_type(field, hints)}` | `{default}` | {meaning} |")
    return "\n".join(rows)


def reference() -> str:
    """The whole reference: root config, blocks, stage keys, algorithms, schedules."""
    from torchrl_stages.config import schema as config
    from torchrl_stages.learners import ALGORITHMS
    from torchrl_stages.schedules import SCHEDULES

    parts = ["## Root config (`stages-train`)", "", table(config.TrainConfig)]
    blocks = [
        ("task", config.TaskConfig),
        ("schedule", config.ScheduleConfig),
        ("logger", config.LoggerConfig),
        ("eval", config.EvalConfig),
        ("objective", config.ObjectiveConfig),
        ("tune (stages-tune only)", config.TuneConfig),
    ]
    for name, cls in blocks:
        parts += ["", f"## `{name}`", "", (inspect.getdoc(cls) or "").split("\n\n")[0], ""]
        parts.append(table(cls))
    parts += [
        "",
        "## Stage keys (`task.stages.<name>`, every algorithm)",
        "",
        (inspect.getdoc(config.StageConfig) or "").split("\n\n")[0],
        "",
        table(config.StageConfig),
    ]
    for name, learner in ALGORITHMS.items():
        cls = learner.Config
        spaces = ", ".join(getattr(learner, "action_spaces", ()))
        parts += [
            "",
            f"## `algo@task.stages.<name>={name}`",
            "",
            f"`{cls.__module__}.{cls.__name__}`; action spaces: {spaces}. Its own keys:",
            "",
            table(cls, own_only=True),
        ]
    for name, schedule in SCHEDULES.items():
        cls = getattr(schedule, "Config", None)
        if cls is not None and dataclasses.is_dataclass(cls):
            parts += ["", f"## `schedule={name}`", "", table(cls, own_only=True)]
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001
    if MARKER in markdown:
        return markdown.replace(MARKER, reference())
    return markdown
