"""Checks of a composed config before anything trains: every key against its field's bound,
the cross-field rules, the env's keys and code; every error names the key and the fix."""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import math
from collections.abc import Callable, Collection
from dataclasses import is_dataclass
from typing import Any

import torch
from hydra.utils import get_object
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_stages.config.expansion import targets
from torchrl_stages.config.schema import (
    ConfigError,
    StageChecks,
    TrainConfig,
    TuneAppConfig,
    check,
    check_bounds,
    nearest,
    schema_keys,
    unknown_key,
)

LOGGER_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow"}
#: the learner class of a stage node (``torchrl_stages.learners.learner_class``)
LearnerClass = Callable[[Any], Any]


def _check_stage(key: str, s: DictConfig, learner_class: LearnerClass) -> None:
    """One stage's keys (``key`` is e.g. ``task.stages.s3``): each against its bound, the
    cross-field rules, then its learner's own checks (``Learner.validate``)."""
    try:
        learner = learner_class(s)
    except ConfigError as err:
        raise ConfigError(f"{key}.{err}") from None
    check_bounds(s, stage_schema(s) or learner.Config, key)
    checks = StageChecks(key, s)
    cnn = {field: list(s[field]) for field in ("cnn_channels", "cnn_kernels", "cnn_strides")}
    checks(
        len(set(map(len, cnn.values()))) == 1,
        "cnn_channels",
        f"needs one entry per conv layer, like {key}.cnn_kernels={cnn['cnn_kernels']} and "
        f"{key}.cnn_strides={cnn['cnn_strides']}",
        "give cnn_channels, cnn_kernels and cnn_strides the same length",
    )
    checks(
        s.frames_per_batch % s.num_envs == 0,
        "frames_per_batch",
        f"must be a multiple of {key}.num_envs={s.num_envs}",
        f"set {key}.frames_per_batch={max(1, s.frames_per_batch // s.num_envs) * s.num_envs}",
    )
    checks(
        s.frames >= s.frames_per_batch,
        "frames",
        f"is smaller than one collector batch ({key}.frames_per_batch={s.frames_per_batch})",
        f"raise {key}.frames or lower {key}.frames_per_batch",
    )
    checks(
        s.batch_size <= s.buffer_size,
        "batch_size",
        f"exceeds {key}.buffer_size={s.buffer_size}",
        f"lower {key}.batch_size",
    )
    learner.validate(checks)


def _check_finite(node: object, prefix: str) -> None:
    """Refuses a NaN or infinite float anywhere under ``node`` (``lr=inf``, ``gamma=nan``):
    no key of the package means anything by them."""
    if isinstance(node, DictConfig | ListConfig):
        items = node.items() if isinstance(node, DictConfig) else enumerate(node)
        for key, value in items:
            _check_finite(value, f"{prefix}.{key}" if prefix else str(key))
    elif isinstance(node, float) and not math.isfinite(node):
        check(False, prefix, node, "must be a finite number", f"set {prefix} to a finite value")


class TargetError(ConfigError):
    """A ``_target_`` of the config names code that cannot be found: its module is not
    importable, fails to import, or has no such name."""


def _first_line(err: BaseException) -> str:
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0] if lines else ''}"


def target_problem(path: str) -> str | None:
    """What is wrong with the dotted ``path`` a ``_target_`` names (``None``: it is found),
    found as Hydra's locate does: the longest importable module, then its attributes.

    Examples:
        >>> target_problem("torchrl_stages.envs.GridWorldEnv") is None
        True
        >>> target_problem("no_such_module.Env").split(".")[0]
        'module `no_such_module` is not importable'
        >>> target_problem("torchrl_stages.envs.GridWorld").split(".")[0]
        'module `torchrl_stages'
        >>> "has no `GridWorld`" in target_problem("torchrl_stages.envs.GridWorld")
        True
    """
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
                return (
                    f"module `{name}` is not importable. Fix: add its directory to PYTHONPATH "
                    "or pip install it"
                )
            return (
                f"module `{where}` has no `{part}`. Fix: check the name (it must be defined at "
                "the top of the module)"
            )
        except Exception as err:  # noqa: BLE001 - the user's module fails on import
            return (
                f"module `{name}` failed to import ({_first_line(err)}). Fix: run "
                f"`python -c 'import {name}'` to see why"
            )
    return None


def check_targets(cfg: DictConfig) -> None:
    """Raises :class:`TargetError` naming the key, the module and the fix for every
    ``_target_`` of ``cfg.task`` (the env, its stage function, a stage's learner) that cannot
    be found. It imports their modules: run it only on configs you trust."""
    container = OmegaConf.to_container(cfg.task, resolve=False)
    for key, target in targets(container, "task"):
        if not isinstance(target, str) or target == "???" or "${" in target:
            continue
        problem = target_problem(target)
        if problem is not None:
            raise TargetError(f"{key}={target}: {problem}")


HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")


def env_arguments(target: str) -> list[str] | None:
    """The keyword arguments the env ``target`` (a dotted class or function) takes; ``None``
    when it takes any (``**kwargs``) or cannot be told.

    Examples:
        >>> "size" in env_arguments("torchrl_stages.envs.GridWorldEnv")
        True
        >>> env_arguments("torchrl_stages.GymStageEnv") is None  # the rest go to gymnasium
        True
    """
    try:
        found = get_object(target)
        function = found.__init__ if isinstance(found, type) else found
        parameters = inspect.signature(function).parameters.values()
    except Exception:  # noqa: BLE001 - not found or no signature: check_targets says which
        return None
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return None
    named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in parameters if p.kind in named and p.name != "self"]


def check_env_arguments(cfg: DictConfig) -> None:
    """Every key of ``task.env`` (and ``task.eval_env``, passed on top of it) is an argument of
    the env it names: a key it lacks (``task.env.env_id`` on a task of its own env, a typo) is
    one line naming the nearest argument, or ``task=gym`` for a gymnasium id."""
    env = cfg.task.get("env")
    target = env.get("_target_") if isinstance(env, DictConfig) else None
    if not isinstance(target, str) or OmegaConf.is_missing(env, "_target_") or "${" in target:
        return
    known = env_arguments(target)
    if known is None:
        return
    task = cfg.task.get("name")
    for node_key in ("env", "eval_env"):
        node = cfg.task.get(node_key)
        if not isinstance(node, DictConfig):
            continue
        values = OmegaConf.to_container(node, resolve=False)
        for name, value in values.items():
            if name in HYDRA_KEYS or name in known:
                continue
            if name == "env_id":  # a gymnasium id given to a task of another env
                raise ConfigError(
                    f"task.{node_key}.env_id={value!r}: task '{task}' builds {target}, which "
                    f"takes no env id. Fix: did you mean task=gym? (task=gym "
                    f"task.env.env_id={value} task.env.stage_fn._target_=my_pkg.my_stage)"
                )
            error = unknown_key(
                f"task.{node_key}",
                name,
                value,
                known,
                f"{target} (the env of task '{task}')",
                f"drop it ({target} takes: {', '.join(known)})",
                what="an argument",
            )
            raise error


def check_env_keys(cfg: DictConfig) -> None:
    """The env's keys can build it: none left ``???``, every ``_target_`` found and every key
    an argument of the env (:func:`check_env_arguments`)."""
    for key in missing_keys(cfg.task.get("env"), "task.env"):
        check(
            False,
            key,
            "???",
            f"task '{cfg.task.name}' leaves it to you (its YAML says what it is)",
            f"set it on the command line: {key}=...",
        )
    check_targets(cfg)
    check_env_arguments(cfg)


def stage_schema(stage: DictConfig) -> type | None:
    """The config dataclass of a composed stage node (``algo@...`` gives it its algorithm's);
    ``None`` for a plain mapping (a run's saved ``config.yaml``, whose keys are its own)."""
    schema = OmegaConf.get_type(stage)
    return schema if is_dataclass(schema) else None


def _check_known(key: str, node: DictConfig, schema: type | None, cfg: DictConfig) -> None:
    """Every key of the stage node ``node`` (at ``key``) is one of ``schema``'s."""
    if schema is None:
        return
    known = schema_keys(schema)
    owner = getattr(schema, "algo", None) or schema.__name__
    listing = f"stages-train task={cfg.task.get('name')} --cfg job"
    for name, value in OmegaConf.to_container(node, resolve=False).items():
        error = unknown_key(key, name, value, known, owner, f"drop it (its keys: {listing})")
        if error is not None:
            raise error


def check_stage_keys(cfg: DictConfig, algorithms: Collection[str]) -> None:
    """Every stage of ``task.stages`` is one of the task's and every key of a stage (and of
    ``task.stage_template``) is one of its algorithm's, whether the command line set it with
    Hydra's ``+`` or without: one line naming the nearest stage or key otherwise."""
    template = cfg.task.get("stage_template")
    template_schema = stage_schema(template) if template else None
    if template:
        _check_known("task.stage_template", template, template_schema, cfg)
    stages = cfg.task.get("stages") or {}
    named = [name for name, stage in stages.items() if _is_stage(stage)]
    for name, stage in stages.items():
        key = f"task.stages.{name}"
        if _is_stage(stage):
            _check_known(key, stage, stage_schema(stage), cfg)
        elif template and isinstance(stage, DictConfig):  # its own keys over the template
            _check_known(key, stage, template_schema, cfg)
        else:
            close = nearest(str(name), named)
            check(
                False,
                key,
                stage,
                f"task '{cfg.task.get('name')}' has no stage {name} (its stages: "
                f"{', '.join(named)})",
                f"did you mean task.stages.{close}?"
                if close
                else f"set a key of one of them, or add the stage with "
                f"+algo@task.stages.{name}=<algo> ({'|'.join(algorithms)})",
            )


def _is_stage(stage: object) -> bool:
    """Whether a ``task.stages`` entry is a stage learner config (it names its algorithm)."""
    return isinstance(stage, DictConfig) and "algo" in stage


def check_device(name: str) -> None:
    """Refuses a CUDA device that torch does not see on this machine."""
    device = torch.device(name)
    if device.type != "cuda":
        return
    check(
        torch.cuda.is_available(),
        "device",
        name,
        "names a CUDA device, but torch sees none on this machine",
        "set device=cpu",
    )
    count = torch.cuda.device_count()
    check(
        device.index is None or device.index < count,
        "device",
        name,
        f"names a GPU this machine does not have (it has {count})",
        "set device=cuda (the first GPU) or a lower index",
    )


def validate_config(
    cfg: DictConfig, schedule: Any, learner_class: LearnerClass, algorithms: Collection[str]
) -> None:
    """Checks what can be checked without building the env (its code is imported: the
    ``_target_`` s must be found); ``schedule`` is the one ``cfg.schedule.name`` names, and
    ``learner_class`` and ``algorithms`` the learners' registry."""
    check_stage_keys(cfg, algorithms)
    _check_finite(cfg.task.get("stages"), "task.stages")  # the env's own keys are its own
    _check_finite(cfg.task.get("stage_template"), "task.stage_template")
    for name in ("eval", "objective"):
        _check_finite(cfg.get(name), name)
    check_env_keys(cfg)
    check_bounds(cfg, TuneAppConfig if "tune" in cfg else TrainConfig, "")
    package = LOGGER_PACKAGES.get(cfg.logger.backend)
    check(
        package is None or importlib.util.find_spec(package) is not None,
        "logger.backend",
        cfg.logger.backend,
        f"needs the '{package}' package, which is not installed",
        f"pip install {package}, or use logger=csv",
    )
    schedule.validate(cfg)
    for key in ("stage_store", "init_from"):
        check(
            not cfg.get(key) or schedule.reuses_stages,
            key,
            cfg.get(key),
            f"schedule={schedule.name} trains its stages together, so a finished stage is not "
            "reusable on its own",
            f"use schedule=backward, or drop {key}",
        )
    check_device(cfg.device)
    check(
        len(cfg.task.stages) > 0,
        "task.stages",
        dict(cfg.task.stages),
        "lists no stage",
        "pick a task with stages, e.g. task=gridworld",
    )
    for name, stage in cfg.task.stages.items():
        _check_stage(f"task.stages.{name}", stage, learner_class)


def missing_keys(node: object, prefix: str) -> list[str]:
    """Dotted keys under ``node`` whose value is ``???`` (to be set by the user).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> missing_keys(OmegaConf.create({"env": {"id": "???", "n": 2}}), "task")
        ['task.env.id']
    """
    if not isinstance(node, DictConfig):
        return []
    out = []
    for key in node.keys():
        if OmegaConf.is_missing(node, key):
            out.append(f"{prefix}.{key}")
        elif not OmegaConf.is_interpolation(node, key):  # ${...} is set: left unresolved
            out += missing_keys(node[key], f"{prefix}.{key}")
    return out


def validate_env_protocol(cfg: DictConfig, env) -> None:
    """Checks what every stage env must have (a built one, ``batch_size=(1,)`` asked): one
    batch dimension that honours the asked size, ``num_stages`` and ``stage_fn``."""
    target = cfg.task.env.get("_target_", "?")
    fix = (
        "accept the batch_size keyword and build a batched env of that size (e.g. with "
        "torchrl's SerialEnv), or use task=gym for a gymnasium env (torchrl_stages.GymStageEnv)"
    )
    check(
        tuple(env.batch_size) == (1,),
        "task.env._target_",
        target,
        f"the env has batch_size={list(env.batch_size)} where batch_size=(1,) was asked: the "
        "stage trainer needs a batched env with one batch dimension [num_envs]",
        fix,
    )
    num_stages = getattr(env, "num_stages", None)
    check(
        isinstance(num_stages, int) and num_stages >= 1,
        "task.env._target_",
        target,
        f"the env has no positive integer num_stages attribute (got {num_stages!r})",
        "give the env class a num_stages attribute (the number of stages it runs through)",
    )
    check(
        hasattr(env, "stage_fn") and (env.stage_fn is None or callable(env.stage_fn)),
        "task.env._target_",
        target,
        "the env has no stage_fn(tensordict) method (nor stage_fn = None with its own "
        '"stage" entry)',
        "add stage_fn(td) returning the stage of each state as int64 [*batch, 1]",
    )


def validate_task(cfg: DictConfig, task, schedule: Any, learner_class: LearnerClass) -> None:
    """Checks the built env against the task protocol, then the stage list and each stage's
    algorithm against its specs."""
    validate_env_protocol(cfg, task.spec_env)
    names = list(cfg.task.stages)
    check(
        len(names) == task.num_stages,
        "task.stages",
        names,
        f"task '{cfg.task.name}' has {task.num_stages} stages but {len(names)} are configured",
        f"configure exactly {task.num_stages} stages (add them with "
        f"+algo@task.stages.NAME=<algo> or remove extra ones with ~task.stages.NAME)",
    )
    schedule.validate_task(cfg, task)
    template = bool(cfg.task.get("stage_template"))
    for k, name in enumerate(names):
        stage = cfg.task.stages[name]
        problem = learner_class(stage).check_action_spec(task.specs(k).action_spec)
        fix = (
            "pick every stage's with algo@task.stage_template=<algo>"
            if template
            else f"override it with algo@task.stages.{name}=<algo>"
        )
        check(problem is None, f"task.stages.{name}.algo", stage.algo, str(problem), fix)


def _direction_name(direction: object) -> str:
    """``maximize`` / ``minimize`` of a sweeper's direction (a string or an enum member)."""
    return str(getattr(direction, "name", direction)).lower()


def validate_sweeper(sweeper: DictConfig | None, cfg: DictConfig) -> None:
    """Checks that a sweeper optimizing a direction (Optuna's ``hydra.sweeper.direction``)
    optimizes the one of ``cfg.objective``: the number a run returns is ``objective.metric``.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"objective": {"metric": "mean_steps", "direction": "minimize"}})
        >>> validate_sweeper(OmegaConf.create({"direction": "minimize"}), cfg)
        >>> validate_sweeper(OmegaConf.create({"direction": "maximize"}), cfg)
        Traceback (most recent call last):
        ...
        torchrl_stages.config.ConfigError: hydra.sweeper.direction='maximize': ...
    """
    if sweeper is None or sweeper.get("direction") is None:
        return
    objective = cfg.objective
    direction = sweeper.direction
    if not isinstance(direction, str) and isinstance(direction, list | tuple | ListConfig):
        check(
            False,
            "hydra.sweeper.direction",
            [_direction_name(d) for d in direction],
            f"a run returns one number (objective.metric={objective.metric})",
            f"set hydra.sweeper.direction={objective.direction}",
        )
    name = _direction_name(direction)
    check(
        name == objective.direction,
        "hydra.sweeper.direction",
        name,
        f"the sweeper would {name} objective.metric={objective.metric}, but "
        f"objective.direction={objective.direction}",
        f"add hydra.sweeper.direction={objective.direction} (Optuna's default is minimize), or "
        f"set objective.direction={name} if a {'lower' if name == 'minimize' else 'higher'} "
        f"{objective.metric} is better",
    )
