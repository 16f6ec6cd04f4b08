"""Checks of a composed config before anything trains; every error names the key and the fix."""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Callable, Collection
from dataclasses import fields, is_dataclass
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_stages.config.bounds import ConfigError, StageChecks, check, check_bounds, check_known
from torchrl_stages.config.env_checks import check_env_keys, validate_env_protocol
from torchrl_stages.config.expansion import leaves
from torchrl_stages.config.schema import TrainConfig, TuneAppConfig

LOGGER_PACKAGES = {"tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow"}

LearnerClass = Callable[[Any], Any]


def _check_stage(key: str, s: DictConfig, learner_class: LearnerClass) -> None:
    """One stage's keys (``key`` is e.g. ``task.stages.s3``), then ``Learner.validate``."""
    try:
        learner = learner_class(s)
    except ConfigError as err:
        raise ConfigError(f"{key}.{err}") from None
    check_bounds(s, stage_schema(s) or learner.Config, key)
    checks = StageChecks(key, s)
    cnn = {field: list(s[field]) for field in ("cnn_channels", "cnn_kernels", "cnn_strides")}
    like = f"{key}.cnn_kernels={cnn['cnn_kernels']} and {key}.cnn_strides={cnn['cnn_strides']}"
    rule = f"needs one entry per conv layer, like {like}"
    fix = "give cnn_channels, cnn_kernels and cnn_strides the same length"
    checks(len(set(map(len, cnn.values()))) == 1, "cnn_channels", rule, fix)
    rule = f"must be a multiple of {key}.num_envs={s.num_envs}"
    fix = f"set {key}.frames_per_batch={max(1, s.frames_per_batch // s.num_envs) * s.num_envs}"
    checks(s.frames_per_batch % s.num_envs == 0, "frames_per_batch", rule, fix)
    rule = f"is smaller than one collector batch ({key}.frames_per_batch={s.frames_per_batch})"
    fix = f"raise {key}.frames or lower {key}.frames_per_batch"
    checks(s.frames >= s.frames_per_batch, "frames", rule, fix)
    rule = f"exceeds {key}.buffer_size={s.buffer_size}"
    checks(s.batch_size <= s.buffer_size, "batch_size", rule, f"lower {key}.batch_size")
    learner.validate(checks)


def stage_schema(stage: DictConfig) -> type | None:
    """The dataclass of a composed stage node; ``None`` for a run's saved ``config.yaml``."""
    schema = OmegaConf.get_type(stage)
    return schema if is_dataclass(schema) else None


def check_stage_keys(cfg: DictConfig, algorithms: Collection[str]) -> None:
    """Refuses a key no stage's schema has, naming the nearest, and a stage the task lacks."""
    template = cfg.task.get("stage_template")
    nodes = {"task.stage_template": (template, template)} if template else {}
    stages = cfg.task.get("stages") or {}
    named = [name for name, stage in stages.items() if _is_stage(stage)]
    for name, stage in stages.items():
        if _is_stage(stage) or (template and isinstance(stage, DictConfig)):
            nodes[f"task.stages.{name}"] = (stage, stage if _is_stage(stage) else template)
            continue
        task = f"task '{cfg.task.get('name')}' (its stages: {', '.join(named)})"
        add = f"+algo@task.stages.{name}=<algo> ({'|'.join(algorithms)})"
        fix = f"set a key of one of them, or add the stage with {add}"
        check_known("task.stages", str(name), stage, named, f"a stage of {task}", fix)
    listing = f"stages-train task={cfg.task.get('name')} --cfg job"
    for key, (node, typed) in nodes.items():
        if (schema := stage_schema(typed)) is None:  # a template's stage: the template's schema
            continue
        what = f"a key of {getattr(schema, 'algo', None) or schema.__name__}"
        known = [f.name for f in fields(schema)]
        for name, value in OmegaConf.to_container(node, resolve=False).items():
            check_known(key, name, value, known, what, f"drop it (its keys: {listing})")


def _is_stage(stage: object) -> bool:
    return isinstance(stage, DictConfig) and "algo" in stage


def validate_config(
    cfg: DictConfig, schedule: Any, learner_class: LearnerClass, algorithms: Collection[str]
) -> None:
    """Checks what can be checked without building the env (it imports the env's code)."""
    check_stage_keys(cfg, algorithms)
    for prefix in ("task.stages", "task.stage_template", "eval", "objective"):  # not the env's
        node = OmegaConf.select(cfg, prefix)
        plain = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        for key, value in leaves(plain, prefix):
            ok = not isinstance(value, float) or math.isfinite(value)
            check(ok, key, value, "must be a finite number", f"set {key} to a finite value")
    check_env_keys(cfg)
    check_bounds(cfg, TuneAppConfig if "tune" in cfg else TrainConfig, "", closed=True)
    package = LOGGER_PACKAGES.get(cfg.logger.backend)
    installed = package is None or importlib.util.find_spec(package) is not None
    rule = f"needs the '{package}' package, which is not installed"
    fix = f"pip install {package}, or use logger=csv"
    check(installed, "logger.backend", cfg.logger.backend, rule, fix)
    schedule.validate(cfg)
    together = f"schedule={schedule.name} trains its stages together"
    for key in ("stage_store", "init_from"):
        rule = f"{together}, so a finished stage is not reusable on its own"
        fix = f"use schedule=backward, or drop {key}"
        check(not cfg.get(key) or schedule.reuses_stages, key, cfg.get(key), rule, fix)
    if (device := torch.device(cfg.device)).type == "cuda":
        rule = "names a CUDA device, but torch sees none on this machine"
        check(torch.cuda.is_available(), "device", cfg.device, rule, "set device=cpu")
        count = torch.cuda.device_count()
        rule = f"names a GPU this machine does not have (it has {count})"
        fix = "set device=cuda (the first GPU) or a lower index"
        check(device.index is None or device.index < count, "device", cfg.device, rule, fix)
    fix = "pick a task with stages, e.g. task=gridworld"
    check(len(cfg.task.stages) > 0, "task.stages", dict(cfg.task.stages), "lists no stage", fix)
    for name, stage in cfg.task.stages.items():
        _check_stage(f"task.stages.{name}", stage, learner_class)


def validate_task(cfg: DictConfig, task, schedule: Any, learner_class: LearnerClass) -> None:
    """Checks the built env, the stage list and each stage's algorithm against its specs."""
    validate_env_protocol(cfg, task.spec_env)
    names = list(cfg.task.stages)
    rule = f"task '{cfg.task.name}' has {task.num_stages} stages but {len(names)} are configured"
    edit = "add them with +algo@task.stages.NAME=<algo> or remove extra ones with ~task.stages.NAME"
    fix = f"configure exactly {task.num_stages} stages ({edit})"
    check(len(names) == task.num_stages, "task.stages", names, rule, fix)
    schedule.validate_task(cfg, task)
    template = bool(cfg.task.get("stage_template"))
    for k, (name, stage) in enumerate(cfg.task.stages.items()):
        problem = learner_class(stage).check_action_spec(task.specs(k).action_spec)
        fix = f"override it with algo@task.stages.{name}=<algo>"
        if template:
            fix = "pick every stage's with algo@task.stage_template=<algo>"
        check(problem is None, f"task.stages.{name}.algo", stage.algo, str(problem), fix)


def _direction_name(direction: object) -> str:
    return str(getattr(direction, "name", direction)).lower()


def validate_sweeper(sweeper: DictConfig | None, cfg: DictConfig) -> None:
    """Refuses a ``hydra.sweeper.direction`` other than ``objective.direction``."""
    if sweeper is None or (direction := sweeper.get("direction")) is None:
        return
    key, metric, wanted = "hydra.sweeper.direction", cfg.objective.metric, cfg.objective.direction
    if isinstance(direction, list | tuple | ListConfig):
        rule = f"a run returns one number (objective.metric={metric})"
        check(False, key, list(map(_direction_name, direction)), rule, f"set {key}={wanted}")
    name = _direction_name(direction)
    rule = f"the sweeper would {name} objective.metric={metric}, but objective.direction={wanted}"
    fix = (
        f"add {key}={wanted} (Optuna's default is minimize), or set objective.direction={name} "
        f"if a {'lower' if name == 'minimize' else 'higher'} {metric} is better"
    )
    check(name == wanted, key, name, rule, fix)
