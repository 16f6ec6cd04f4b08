"""The doctests of a module that needs an optional extra skip, with the reason, where that extra
is not installed (the tests of ``tests/`` skip the same way)."""

import importlib.util
from pathlib import Path

import pytest

#: folder -> (module it needs, the extra that installs it)
EXTRAS = {
    Path(__file__).parent / "envs" / "minigrid": ("minigrid", "minigrid"),
    Path(__file__).parent / "envs" / "metaworld": ("metaworld", "metaworld"),
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for folder, (module, extra) in EXTRAS.items():
        if importlib.util.find_spec(module) is not None:
            continue
        reason = f"the {extra} extra is not installed: pip install '.[{extra}]'"
        skip = pytest.mark.skip(reason=reason)
        for item in items:
            if Path(item.path).is_relative_to(folder):
                item.add_marker(skip)
