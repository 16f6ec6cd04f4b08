"""The package's tasks, installed as ``torchrl_stages.envs``: one sub-package each (its env,
report and figures; its ``__init__`` registers the task) and its ``conf/task/<task>.yaml``.
Every sub-package's public names are re-exported here, so a task is its folder and its YAML."""

import importlib
import pkgutil

__all__: list[str] = []
for _task in pkgutil.iter_modules(__path__):
    if _task.ispkg:
        _module = importlib.import_module(f"{__name__}.{_task.name}")
        globals().update({name: getattr(_module, name) for name in _module.__all__})
        __all__ += _module.__all__
