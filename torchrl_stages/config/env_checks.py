"""Checks of a task's env: its keys, the code its ``_target_`` s name, and a built env."""

from __future__ import annotations

import importlib
import inspect

from hydra.utils import get_object
from omegaconf import DictConfig, OmegaConf

from torchrl_stages.config.bounds import ConfigError, check, check_known
from torchrl_stages.config.expansion import leaves, targets

HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")


class TargetError(ConfigError):
    """A ``_target_`` of the config names code that cannot be found."""


def _first_line(err: BaseException) -> str:
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0] if lines else ''}"


def target_problem(path: str) -> str | None:
    """What is wrong with the dotted ``path`` a ``_target_`` names (``None``: it is found)."""
    parts = path.split(".")
    if not all(parts):
        return f"`{path}` is not a dotted path. Fix: name it as my_module.MyClass"
    found, where = None, ""
    for index, part in enumerate(parts):
        name = ".".join(parts[: index + 1])
        if found is not None and hasattr(found, part):
            found, where = getattr(found, part), name
            continue
        try:
            found, where = importlib.import_module(name), name
        except ModuleNotFoundError as err:
            if err.name != name:  # a module it imports is missing
                return f"module `{name}` failed to import ({_first_line(err)}). Fix: install it"
            if index == 0:
                fix = "add its directory to PYTHONPATH or pip install it"
                return f"module `{name}` is not importable. Fix: {fix}"
            fix = "check the name (it must be defined at the top of the module)"
            return f"module `{where}` has no `{part}`. Fix: {fix}"
        except Exception as err:  # noqa: BLE001 - the user's module fails on import
            fix = f"run `python -c 'import {name}'` to see why"
            return f"module `{name}` failed to import ({_first_line(err)}). Fix: {fix}"
    return None


def check_env_arguments(cfg: DictConfig) -> None:
    """Refuses a key of ``task.env`` or ``task.eval_env`` the env takes no argument for."""
    target = cfg.task.env.get("_target_")
    try:
        found = get_object(target)
        function = found.__init__ if isinstance(found, type) else found
        parameters = inspect.signature(function).parameters.values()
    except Exception:  # noqa: BLE001 - no _target_, or no signature
        return
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return
    named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    known = [p.name for p in parameters if p.kind in named and p.name != "self"]
    task = cfg.task.get("name")
    what = f"an argument of {target} (the env of task '{task}')"
    drop = f"drop it ({target} takes: {', '.join(known)})"
    for node_key in ("env", "eval_env"):
        node = cfg.task.get(node_key)
        values = OmegaConf.to_container(node, resolve=False) if node is not None else {}
        for name, value in values.items():
            if name in HYDRA_KEYS or name in known:
                continue
            if name == "env_id":  # a gymnasium id given to a task of another env
                rule = f"task '{task}' builds {target}, which takes no env id"
                gym = f"task.env.env_id={value} task.env.stage_fn._target_=my_pkg.my_stage"
                fix = f"did you mean task=gym? (task=gym {gym})"
                check(False, f"task.{node_key}.env_id", value, rule, fix)
            check_known(f"task.{node_key}", name, value, known, what, drop)


def check_env_keys(cfg: DictConfig) -> None:
    """The env's keys: none left ``???``, each ``_target_`` found (imported), each an argument."""
    for key in missing_keys(cfg.task.get("env"), "task.env"):
        rule = f"task '{cfg.task.name}' leaves it to you (its YAML says what it is)"
        check(False, key, "???", rule, f"set it on the command line: {key}=...")
    for key, target in targets(OmegaConf.to_container(cfg.task, resolve=False), "task"):
        given = isinstance(target, str) and target != "???" and "${" not in target
        if given and (problem := target_problem(target)):
            raise TargetError(f"{key}={target}: {problem}")
    check_env_arguments(cfg)


def missing_keys(node: object, prefix: str) -> list[str]:
    """Dotted keys under ``node`` whose value is ``???``.

    Examples:
        >>> missing_keys(OmegaConf.create({"env": {"id": "???", "n": 2}}), "task")
        ['task.env.id']
    """
    plain = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    return [key for key, value in leaves(plain, prefix) if value == "???"]


def validate_env_protocol(cfg: DictConfig, env) -> None:
    """Checks a built stage env (``batch_size=(1,)`` asked): its batch size, ``num_stages``
    and ``stage_fn``."""
    num_stages = getattr(env, "num_stages", None)
    rules = [
        (
            tuple(env.batch_size) == (1,),
            f"the env has batch_size={list(env.batch_size)} where batch_size=(1,) was asked: the "
            "stage trainer needs a batched env with one batch dimension [num_envs]",
            "accept the batch_size keyword and build a batched env of that size (e.g. with "
            "torchrl's SerialEnv), or use task=gym for a gymnasium env "
            "(torchrl_stages.GymStageEnv)",
        ),
        (
            isinstance(num_stages, int) and num_stages >= 1,
            f"the env has no positive integer num_stages attribute (got {num_stages!r})",
            "give the env class a num_stages attribute (the number of stages it runs through)",
        ),
        (
            hasattr(env, "stage_fn") and (env.stage_fn is None or callable(env.stage_fn)),
            'the env has no stage_fn(tensordict) method (nor stage_fn = None with its own "stage" '
            "entry)",
            "add stage_fn(td) returning the stage of each state as int64 [*batch, 1]",
        ),
    ]
    for ok, rule, fix in rules:
        check(ok, "task.env._target_", cfg.task.env.get("_target_", "?"), rule, fix)
