"""Presets and help: the ``experiment`` group and ``all_stages``, the per-task stage defaults,
the ``objective`` block, and ``stages-train --help``. Compositions run in-process; ``--help`` and
a smoke run with a stage added on the command line are subprocesses."""

from __future__ import annotations

import importlib.resources
import logging
import re

import pytest
from helpers import run_cli, validate
from omegaconf import OmegaConf

from torchrl_stages.config import ConfigError, apply_all_stages, stage_keys_set
from torchrl_stages.config.checks import validate_sweeper
from torchrl_stages.runs.experiment import Experiment
from torchrl_stages.runs.seed_run import with_env_stages

CONF = importlib.resources.files("torchrl_stages.conf")
SMOKE = OmegaConf.create(CONF.joinpath("experiment/smoke.yaml").read_text()).all_stages
SHIPPED = {"gridworld": [f"s{k}" for k in range(5)], "manipulator": ["coarse", "fine"]}
SHIPPED["cargo"] = ["slider", "propelled"]


def options(group: str) -> list[str]:
    return sorted(
        p.name.removesuffix(".yaml")
        for p in CONF.joinpath(group).iterdir()
        if p.is_file() and p.name.endswith(".yaml")
    )


def compose_run(hydra_compose, *overrides: str):
    """The config ``stages-train`` runs: composed, then ``all_stages`` applied."""
    return apply_all_stages(hydra_compose(*overrides), keep=stage_keys_set(overrides))


# ------------------------------------------------------------------ experiment=smoke
@pytest.mark.parametrize("task", options("task"))
def test_smoke_gives_every_stage_of_every_task_its_budget(hydra_compose, task):
    full = hydra_compose(f"task={task}")
    smoke = compose_run(hydra_compose, f"task={task}", "experiment=smoke")
    assert list(smoke.task.stages) == list(full.task.stages)
    stages, full_stages = dict(smoke.task.stages.items()), dict(full.task.stages.items())
    if full.task.stage_template:  # the stages the env decides on are made from it
        stages["stage_template"] = smoke.task.stage_template
        full_stages["stage_template"] = full.task.stage_template
    for name, stage in stages.items():
        for key, value in SMOKE.items():
            assert stage[key] == value, (name, key)
        # everything else is the task's own
        for key in ("gamma", "lr", "num_cells", "algo", "tau"):
            assert stage[key] == full_stages[name][key], (name, key)
    assert smoke.eval.episodes == 32
    if task in SHIPPED:  # the env templates leave their env keys to the user
        validate(smoke)


LINE = ("task.env.env_id=line_env:LineWorld-v0", "task.env.stage_fn._target_=line_env.line_stage")


def test_stages_come_from_the_env_each_with_the_template_and_smoke(hydra_compose):
    overrides = ("task=gym", "experiment=smoke", *LINE, "task.env.num_stages=3")
    overrides += ("+task.stages.s2.frames=512", "+task.stages.s1.lr=1e-4")
    cfg = with_env_stages(compose_run(hydra_compose, *overrides))
    assert list(cfg.task.stages) == ["s0", "s1", "s2"]  # as many as the env has
    template = hydra_compose("task=gym").task.stage_template
    for name, stage in cfg.task.stages.items():
        assert stage.updates_per_batch == SMOKE.updates_per_batch  # smoke reaches every stage
        assert stage.value_tolerance == template.value_tolerance  # the template's keys
        assert stage.frames == (512 if name == "s2" else SMOKE.frames)  # a stage's own wins
        assert stage.lr == (1e-4 if name == "s1" else template.lr)
    assert with_env_stages(cfg) == cfg  # expanding again changes nothing


def test_a_stage_past_the_envs_last_is_named(hydra_compose):
    cfg = hydra_compose("task=gym", *LINE, "+task.stages.s5.lr=1e-3")
    with pytest.raises(ConfigError, match=r"task\.stages\.s5: the env has 2 stages, named s0, s1"):
        with_env_stages(cfg)


def test_all_stages_names_a_key_a_stage_lacks(hydra_compose):
    with pytest.raises(ConfigError, match=r"all_stages\.double_dqn=True: task\.stages\.coarse"):
        compose_run(hydra_compose, "task=manipulator", "+all_stages.double_dqn=true")


def test_smoke_composes_with_other_overrides(hydra_compose):
    cfg = compose_run(
        hydra_compose,
        "experiment=smoke",
        "algo@task.stages.s0=td3",
        "task.stages.s1.frames=512",
        "task/gammas=hetero",
        "eval.episodes=3",
    )
    assert cfg.task.stages.s0.algo == "td3" and cfg.task.stages.s0.frames == SMOKE.frames
    assert cfg.task.stages.s1.frames == 512  # the command line wins over the preset
    assert [cfg.task.stages[s].gamma for s in SHIPPED["gridworld"]] == [0.9, 0.9, 0.9, 0.99, 0.9]
    assert cfg.eval.episodes == 3


def test_a_smoke_run_warns_of_nothing(hydra_compose, tmp_path, caplog):
    # its budget is short on purpose: no stage is told to raise its frames
    two_stages = ["task.env.size=10", "task.env.num_stages=2", "~task.stages.s2"]
    two_stages += ["~task.stages.s3", "~task.stages.s4", "eval.plots=false"]
    cfg = compose_run(hydra_compose, "experiment=smoke", *two_stages)
    with caplog.at_level(logging.INFO, logger="torchrl_stages"):
        Experiment(cfg, tmp_path / "run").run()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []
    assert sum("dqn): 1024 frames" in r.getMessage() for r in caplog.records) == 2


def test_without_an_experiment_no_preset_applies(hydra_compose):
    cfg = hydra_compose()
    assert cfg.task.stages.s0.frames != SMOKE.frames and cfg.eval.episodes == 100


# ------------------------------------------------------------------ per-task stage defaults
@pytest.mark.parametrize("task", sorted(SHIPPED))
def test_shared_stage_keys_reach_every_stage(hydra_compose, task):
    # the task file's stages (its shared keys merged in by YAML anchors) are what composes
    written = OmegaConf.create(CONF.joinpath(f"task/{task}.yaml").read_text()).stages
    shared = written[SHIPPED[task][-1]]
    cfg = hydra_compose(f"task={task}")
    assert list(cfg.task.stages) == SHIPPED[task]
    for name in SHIPPED[task]:
        assert set(shared) <= set(written[name])  # every stage has the shared keys
        for key, value in written[name].items():
            if task == "gridworld" and key == "gamma":
                continue  # the discount preset follows
            assert cfg.task.stages[name][key] == value, (name, key)


def test_stage_overrides_still_apply(hydra_compose):
    cfg = hydra_compose("task=manipulator", "algo@task.stages.fine=td3", "task.stages.fine.lr=5e-4")
    fine, coarse = cfg.task.stages.fine, cfg.task.stages.coarse
    assert fine.algo == "td3" and fine.lr == 5e-4 and fine.num_cells == [256, 256]
    assert coarse.algo == "ddpg" and coarse.lr == 1e-3
    cargo = hydra_compose("task=cargo")
    assert cargo.task.stages.slider.updates_per_batch == 64  # its own key over the shared 32
    assert cargo.task.stages.propelled.updates_per_batch == 32
    assert cargo.task.stages.propelled.gamma == 0.99 and cargo.task.stages.slider.gamma == 0.98


# ------------------------------------------------------------------ objective
def test_objective_defaults_and_validation(hydra_compose):
    cfg = hydra_compose()
    assert (cfg.objective.metric, cfg.objective.direction) == ("success_rate", "maximize")
    validate(hydra_compose("objective.metric=mean_steps", "objective.direction=minimize"))
    for override, key in (
        ("objective.metric=reward", "objective.metric"),
        ("objective.direction=up", "objective.direction"),
    ):
        with pytest.raises(ConfigError, match=rf"{re.escape(key)}=.*Fix:"):
            validate(hydra_compose(override))


def test_sweeper_direction_must_match_the_objective(hydra_compose):
    cfg = hydra_compose()
    validate_sweeper(None, cfg)  # the basic sweeper optimizes nothing
    validate_sweeper(OmegaConf.create({"max_batch_size": None}), cfg)
    validate_sweeper(OmegaConf.create({"direction": "maximize"}), cfg)
    with pytest.raises(ConfigError, match=r"hydra\.sweeper\.direction='minimize'.*Fix: add "):
        validate_sweeper(OmegaConf.create({"direction": "minimize"}), cfg)
    with pytest.raises(ConfigError, match="one number"):
        validate_sweeper(OmegaConf.create({"direction": ["maximize", "minimize"]}), cfg)


# ------------------------------------------------------------------ --help
@pytest.mark.e2e
def test_help_describes_the_app(tmp_path):
    # the help shows the values of the composed config (task=cargo: 1000 evaluation episodes)
    result = run_cli(["stages-train", "task=cargo", "--help"], cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    text = result.stdout
    assert text.startswith("stages-train: Stacked Deep Q-Learning")
    assert "_schema" not in text  # internal schema entries stay hidden
    for group, line_start in [
        ("task", "task="),
        ("algo", "algo@task.stages.<stage>="),
        ("schedule", "schedule="),
        ("experiment", "experiment="),
        ("logger", "logger="),
        ("task/gammas", "task/gammas="),
    ]:
        listed = set()
        for line in text.splitlines():
            if line.startswith(line_start):
                listed |= set(line.split()[0].removeprefix(line_start).split("|"))
        assert set(options(group)) <= listed, (group, listed)
    for key in ("objective.metric=success_rate", "seed=0", "eval.episodes=1000", "resume=False"):
        assert key in text
    assert "stages-train -m experiment=smoke seed=0,1" in text
    assert "--multirun,-m" in text  # Hydra's flags
