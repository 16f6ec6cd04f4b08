"""Composition of the shipped Hydra configs, the typed schemas, and validation before training.

Everything here runs in-process through Hydra's compose API (no training, no subprocess).
"""

from __future__ import annotations

import copy
import importlib.resources
import importlib.util
import re
from dataclasses import Field, fields, is_dataclass

import pytest
import torch
from helpers import run_cli, validate
from hydra.errors import ConfigCompositionException
from omegaconf import DictConfig, OmegaConf, open_dict

from torchrl_stages.config import (
    ConfigError,
    LoggerConfig,
    StageConfig,
    apply_all_stages,
    as_dataclass,
)
from torchrl_stages.config.bounds import Bound
from torchrl_stages.config.registration import by_prefix
from torchrl_stages.config.schema import TuneAppConfig, TuneConfig
from torchrl_stages.learners import ALGORITHMS, make_learner
from torchrl_stages.learners.ddpg import DDPGConfig
from torchrl_stages.learners.dqn import DQNConfig
from torchrl_stages.learners.td3 import TD3Config
from torchrl_stages.runs.experiment import Experiment, build_task
from torchrl_stages.runs.seed_run import with_env_stages
from torchrl_stages.schedules import BackwardSchedule

CONF = importlib.resources.files("torchrl_stages.conf")
# the grid world's per-stage frame budget, as its YAML sets it (keys shared by every stage)
GRID_FRAMES = OmegaConf.create(CONF.joinpath("task/gridworld.yaml").read_text()).stages.s0.frames
STAGES = [f"s{k}" for k in range(5)]


def _options(group: str) -> list[str]:
    """Names of the YAML options shipped in ``conf/<group>/`` (listed, not hard-coded)."""
    names = sorted(
        p.name.removesuffix(".yaml")
        for p in CONF.joinpath(group).iterdir()
        if p.is_file() and p.name.endswith(".yaml")
    )
    assert names, f"no options found in conf/{group}"
    return names


TASKS = _options("task")
GAMMAS = _options("task/gammas")
ALGOS = _options("algo")
LOGGERS = _options("logger")


def _gammas(cfg: DictConfig) -> list[float]:
    return [float(cfg.task.stages[name].gamma) for name in cfg.task.stages]


def _error_text(err: BaseException) -> str:
    """The message of ``err`` and of every exception in its ``__cause__``/``__context__`` chain."""
    parts = []
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        parts.append(str(err))
        err = err.__cause__ or err.__context__
    return "\n".join(parts)


# ------------------------------------------------------------------ shipped configs compose
def test_shipped_groups_are_found():
    assert "gridworld" in TASKS
    assert {"homo", "hetero"} <= set(GAMMAS)
    assert {"dqn", "ddpg", "td3"} <= set(ALGOS)
    assert {"csv", "none"} <= set(LOGGERS)
    assert set(ALGOS) == set(ALGORITHMS)


def test_default_config(hydra_compose):
    cfg = hydra_compose()
    assert cfg.task.name == "gridworld"
    assert list(cfg.task.stages) == STAGES
    assert cfg.logger.backend == "csv"
    assert cfg.logger.exp_name == "gridworld"  # ${task.name} resolves
    assert _gammas(cfg) == [0.99] * 5  # the default gammas preset is homo
    assert cfg.seed == 0 and cfg.device == "cpu"
    # the task's YAML values land on top of the schema defaults
    assert cfg.task.stages.s2.frames == GRID_FRAMES and cfg.task.stages.s2.fourier_features == 3
    validate(cfg)


# the keys the env templates leave to the user (tests/line_env.py registers LineWorld-v0)
TEMPLATE_KEYS = {
    "gym": (
        "schedule=joint",
        "task.env.env_id=line_env:LineWorld-v0",
        "task.env.stage_fn._target_=line_env.line_stage",
    ),
    "custom": (
        "task.env._target_=torchrl_stages.envs.GridWorldEnv",
        "+task.env.size=10",
        "+task.env.num_stages=2",
    ),
}


@pytest.mark.parametrize("task", TASKS)
def test_every_task_composes_and_builds(hydra_compose, task):
    cfg = hydra_compose(f"task={task}", *TEMPLATE_KEYS.get(task, ()))
    assert cfg.task.name
    assert len(cfg.task.stages) > 0 or cfg.task.stage_template  # else from the env
    built = build_task(cfg)  # validates, builds the env, checks stages against its specs
    assert built.num_stages == len(built.cfg.stages)


@pytest.mark.parametrize("gammas", GAMMAS)
def test_every_gammas_preset_composes(hydra_compose, gammas):
    cfg = hydra_compose(f"task/gammas={gammas}")
    gs = _gammas(cfg)
    assert len(gs) == 5 and all(0 < g <= 1 for g in gs)
    validate(cfg)


@pytest.mark.parametrize("algo", ALGOS)
def test_every_algo_option_composes_on_a_stage(hydra_compose, algo):
    # The action-space mismatch (DDPG/TD3 on the grid world) is found at validation, not here.
    stage = "s0"
    cfg = hydra_compose(f"algo@task.stages.{stage}={algo}", "task/gammas=hetero")
    node = cfg.task.stages[stage]
    assert node.algo == algo
    assert OmegaConf.get_type(node) is ALGORITHMS[algo].Config
    # the task's per-stage values and the gammas preset still apply on top of the new schema
    assert node.frames == GRID_FRAMES
    assert node.gamma == 0.9  # hetero
    others = [OmegaConf.get_type(cfg.task.stages[s]) for s in STAGES if s != stage]
    assert others == [DQNConfig] * 4
    validate(cfg)  # ranges are fine; only the env check rejects continuous algos


@pytest.mark.parametrize("logger", LOGGERS)
def test_every_logger_option_composes(hydra_compose, logger):
    cfg = hydra_compose(f"logger={logger}")
    assert cfg.logger.backend == logger
    assert OmegaConf.get_type(cfg.logger) is LoggerConfig
    assert cfg.logger.exp_name == "gridworld"
    if logger in ("csv", "none"):  # the others need their (optional) package at validation
        validate(cfg)


# ------------------------------------------------------------------ gammas presets
def test_hetero_gammas(hydra_compose):
    assert _gammas(hydra_compose("task/gammas=hetero")) == [0.9, 0.9, 0.9, 0.99, 0.9]


def test_homo_gammas(hydra_compose):
    assert _gammas(hydra_compose("task/gammas=homo")) == [0.99] * 5


@pytest.mark.parametrize("preset", ["homo", "hetero"])
def test_gamma_override_after_preset_wins(hydra_compose, preset):
    cfg = hydra_compose(f"task/gammas={preset}", "task.stages.s3.gamma=0.95")
    assert cfg.task.stages.s3.gamma == 0.95
    expected = {"homo": 0.99, "hetero": 0.9}[preset]
    assert [cfg.task.stages[s].gamma for s in ("s0", "s1", "s2", "s4")] == [expected] * 4


def test_gamma_override_wins_regardless_of_order(hydra_compose):
    cfg = hydra_compose("task.stages.s3.gamma=0.95", "task/gammas=hetero")
    assert _gammas(cfg) == [0.9, 0.9, 0.9, 0.95, 0.9]


# ------------------------------------------------------------------ typed schema
def test_stage_nodes_are_typed(hydra_compose):
    cfg = hydra_compose()
    for name in STAGES:
        assert OmegaConf.get_type(cfg.task.stages[name]) is DQNConfig
    assert OmegaConf.get_type(hydra_compose("algo@task.stages.s1=ddpg").task.stages.s1) is (
        DDPGConfig
    )
    assert OmegaConf.get_type(hydra_compose("algo@task.stages.s1=td3").task.stages.s1) is (
        TD3Config
    )


def test_learners_read_their_composed_stage_config_as_a_dataclass(hydra_compose):
    cfg = hydra_compose("task.stages.s1.tau=0.125")
    task = build_task(cfg)
    learner = make_learner(task.stage_cfg(1), task.specs(1))
    assert type(learner.cfg) is DQNConfig  # plain attribute reads in the update
    assert learner.cfg.tau == 0.125 and learner.cfg.gamma == cfg.task.stages.s1.gamma
    # anything that is not a structured node is kept as given
    plain = OmegaConf.create({"gamma": 0.5})
    assert as_dataclass(plain) is plain
    missing = OmegaConf.structured(DQNConfig)
    missing.gamma = "???"
    assert as_dataclass(missing) is missing
    instance = DQNConfig()
    assert as_dataclass(instance) is instance


# ------------------------------------------------------------------ keys as messages write them
LINE = TEMPLATE_KEYS["gym"][1:]  # a gymnasium env of two stages (tests/line_env.py)


@pytest.mark.parametrize(
    ("template", "override"),
    [
        (("task=gym", *LINE), "task.stages.s1.frames=4096"),
        (("task=gym", *LINE), "+task.stages.s1.frames=4096"),
        (("task=custom", *TEMPLATE_KEYS["custom"]), "task.stages.s1.frames=4096"),
    ],
)
def test_a_template_tasks_stage_key_is_set_as_on_any_task(hydra_compose, template, override):
    # the form every message prints (Fix: raise task.stages.s1.frames) works without `+`
    cfg = with_env_stages(hydra_compose(*template, override))
    assert list(cfg.task.stages) == ["s0", "s1"]
    assert cfg.task.stages.s1.frames == 4096
    assert cfg.task.stages.s0.frames == cfg.task.stage_template.frames != 4096
    validate(cfg)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        # written without `+` or with it, on a task of its own stages or a template task
        (["task.stages.s0.lrr=1e-3"], "task.stages.s0.lrr=0.001: not a key of dqn. "),
        (["+task.stages.s0.lrr=1e-3"], "task.stages.s0.lrr=0.001: not a key of dqn. "),
        (["task=gym", *LINE, "+task.stage_template.lrr=1e-3"], "task.stage_template.lrr="),
        (["task=gym", *LINE, "task.stage_template.lrr=1e-3"], "task.stage_template.lrr="),
        (["task=gym", *LINE, "task.stages.s1.lrr=1e-3"], "task.stages.s1.lrr="),
        (["task=manipulator", "+task.stages.fine.sigma_ini=0.3"], "of ddpg. "),
    ],
)
def test_an_unknown_stage_key_is_one_line_naming_the_nearest(
    hydra_compose, tmp_path, overrides, message
):
    cfg = hydra_compose(*overrides)
    with pytest.raises(ConfigError) as info:
        Experiment(cfg, tmp_path / "run")  # refused before the run directory is made
    text = str(info.value)
    assert message in text and "\n" not in text, text
    key = overrides[-1].lstrip("+").split("=")[0]
    nearest = key.replace("lrr", "lr").replace("sigma_ini", "sigma_init")
    assert f"Fix: did you mean {nearest}?" in text, text
    assert not (tmp_path / "run").exists()


def test_an_all_stages_typo_names_the_nearest_key(hydra_compose):
    expected = r"^all_stages\.lrr=0\.001: task\.stages\.s0 .*Fix: did you mean all_stages\.lr\?$"
    with pytest.raises(ConfigError, match=expected):
        apply_all_stages(hydra_compose("+all_stages.lrr=1e-3"))


def test_a_stage_the_task_does_not_have_is_named_with_its_stages(hydra_compose):
    with pytest.raises(ConfigError) as info:
        validate(hydra_compose("task=manipulator", "task.stages.fin.lr=1e-3"))
    text = str(info.value)
    assert text.startswith("task.stages.fin=") and "task 'manipulator'" in text, text
    assert "coarse, fine" in text and "did you mean task.stages.fine?" in text, text


@pytest.mark.parametrize("plus", ["", "+"])
def test_an_env_id_without_task_gym_suggests_it(hydra_compose, plus):
    cfg = hydra_compose(f"{plus}task.env.env_id=CartPole-v1")
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    text = str(info.value)
    assert text.startswith("task.env.env_id='CartPole-v1': task 'gridworld'"), text
    assert "Fix: did you mean task=gym?" in text and "\n" not in text, text


def test_an_env_argument_the_env_lacks_names_the_nearest(hydra_compose):
    with pytest.raises(ConfigError) as info:
        validate(hydra_compose("task.env.max_step=30"))
    text = str(info.value)
    assert text.startswith("task.env.max_step=30: not an argument of torchrl_stages.envs."), text
    assert "did you mean task.env.max_steps?" in text, text


def test_unknown_root_key_fails_at_composition(hydra_compose):
    with pytest.raises(ConfigCompositionException) as info:
        hydra_compose("sed=1")
    assert "sed" in _error_text(info.value)


@pytest.mark.parametrize(
    "override",
    ["task.stages.s0.gamma=abc", "task.stages.s4.frames=many", "seed=zero"],
)
def test_wrong_type_fails_at_composition(hydra_compose, override):
    key = override.split("=")[0]
    with pytest.raises(ConfigCompositionException) as info:
        hydra_compose(override)
    assert key.split(".")[-1] in _error_text(info.value)


def test_typed_values_are_converted(hydra_compose):
    cfg = hydra_compose("task.stages.s0.gamma=1", "task.stages.s0.frames=4096")
    assert isinstance(cfg.task.stages.s0.gamma, float) and cfg.task.stages.s0.gamma == 1.0
    assert isinstance(cfg.task.stages.s0.frames, int)


# ------------------------------------------------------------------ validation
# Command-line overrides -> substrings the ConfigError message must contain.
INVALID = {
    "gamma_zero": (["task.stages.s2.gamma=0"], ["task.stages.s2.gamma", "(0, 1]"]),
    "gamma_above_one": (["task.stages.s2.gamma=1.5"], ["task.stages.s2.gamma", "(0, 1]"]),
    "ddpg_on_discrete": (["algo@task.stages.s1=ddpg"], ["task.stages.s1.algo", "continuous"]),
    "td3_on_discrete": (["algo@task.stages.s4=td3"], ["task.stages.s4.algo", "continuous"]),
    "stage_removed": (["~task.stages.s4"], ["task.stages", "5 stages"]),
    "stage_added": (["+algo@task.stages.s5=dqn"], ["task.stages", "5 stages"]),
    "frames_per_batch": (
        ["task.stages.s3.frames_per_batch=100"],  # the grid world's num_envs is 256
        ["task.stages.s3.frames_per_batch", "multiple", "num_envs"],
    ),
    "batch_over_buffer": (
        ["task.stages.s1.buffer_size=128"],  # the grid world's batch_size is 256
        ["task.stages.s1.batch_size", "task.stages.s1.buffer_size"],
    ),
    "logger_backend": (["logger.backend=neptune"], ["logger.backend", "csv"]),
    "env_size": (["task.env.size=24"], ["task.env"]),  # 24 is no multiple of 5 stages
    "env_target": (["task.env._target_=torchrl_stages.envs.NoSuchEnv"], ["task.env"]),
}


@pytest.mark.parametrize("case", list(INVALID))
def test_invalid_config_raises_config_error(hydra_compose, case):
    overrides, needles = INVALID[case]
    cfg = hydra_compose(*overrides)
    with pytest.raises(ConfigError) as info:
        build_task(cfg)
    message = str(info.value)
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"
    assert "Fix:" in message


@pytest.mark.parametrize(
    "case", ["gamma_zero", "gamma_above_one", "frames_per_batch", "batch_over_buffer"]
)
def test_range_errors_are_found_without_building_the_env(hydra_compose, case):
    overrides, needles = INVALID[case]
    with pytest.raises(ConfigError, match="Fix:") as info:
        validate(hydra_compose(*overrides))
    assert needles[0] in str(info.value)


# Rules a field's bound does not say: cross-field, a list's length.
OUT_OF_RANGE = [
    ("task.stages.s3.frames", 128),  # smaller than one collector batch (256)
    ("task.stages.s4.num_cells", []),
    ("task.stages.s4.cnn_channels", [16]),  # one entry per conv layer, like cnn_kernels
]


@pytest.mark.parametrize(("key", "value"), OUT_OF_RANGE)
def test_out_of_range_value_raises_config_error(hydra_compose, key, value):
    cfg = copy.deepcopy(hydra_compose())
    OmegaConf.update(cfg, key, value, merge=False)
    with pytest.raises(ConfigError) as info:
        validate(cfg)
    message = str(info.value)
    assert message.startswith(f"{key}="), message
    assert "Fix:" in message


# ------------------------------------------------------------------ declared bounds
SCHEMAS = [TuneAppConfig, StageConfig, *(learner.Config for learner in ALGORITHMS.values())]


def _fields(schema: type, prefix: str = "") -> list[tuple[str, Field]]:
    """``(key, field)`` of every field of ``schema``, its blocks' fields included."""
    out = []
    for f in fields(schema):
        key = f"{prefix}{f.name}"
        if is_dataclass(f.default_factory):
            out += _fields(f.default_factory, f"{key}.")
        else:
            out.append((key, f))
    return out


def _outside(f: Field) -> list:
    """Values just outside the bound of ``f`` (none for a free field or a flag: its type bounds
    it)."""
    bound = f.metadata["bound"]
    if bound.free or bound.choices == (True, False):
        return []
    if bound.choices:
        return ["no_such_choice"]
    if bound.pattern:
        return ["meta"]
    values = [bound.low if bound.low_open else bound.low - 1]
    if bound.high is not None:
        values.append(bound.high if bound.high_open else bound.high + 1)
    return [[v] if str(f.type).startswith("list") else v for v in values]


@pytest.mark.parametrize("schema", SCHEMAS, ids=lambda schema: schema.__name__)
def test_every_config_field_declares_a_bound_or_free(schema):
    for key, f in _fields(schema):
        assert isinstance(f.metadata.get("bound"), Bound), f"{schema.__name__}.{key}"


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_a_value_outside_its_bound_is_refused_naming_the_key(hydra_compose, algo):
    base = copy.deepcopy(hydra_compose(f"algo@task.stages.s0={algo}"))
    with open_dict(base):
        base.tune = OmegaConf.structured(TuneConfig)
    cases = [(f"task.stages.s0.{key}", f) for key, f in _fields(ALGORITHMS[algo].Config)]
    if algo == "dqn":  # the root's keys once
        cases += _fields(TuneAppConfig)
    checked = 0
    for key, f in cases:
        for value in _outside(f):
            cfg = copy.deepcopy(base)
            OmegaConf.update(cfg, key, value, merge=False)
            with pytest.raises(ConfigError) as info:
                validate(cfg)
            message = str(info.value)
            assert message.startswith(f"{key}=") and "Fix:" in message, message
            assert "\n" not in message, message
            checked += 1
    assert checked > 20


@pytest.mark.parametrize(
    "override",
    [
        "task.stages.s0.max_grad_norm=-1",
        "task.stages.s0.lr_end_factor=-1",
        "task.stages.s0.fourier_features=-1",
        "task.stages.s0.value_error_reduce=median",
        "task.stages.s0.updates_per_batch=0",
        "seed=-1",
        "device=meta",
    ],
)
def test_a_value_that_would_train_nonsense_is_refused_before_the_run(
    hydra_compose, tmp_path, override
):
    with pytest.raises(ConfigError, match=rf"^{re.escape(override.split('=')[0])}=.*Fix:"):
        Experiment(hydra_compose(override), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


@pytest.mark.parametrize("gamma", ["1.0", "1e-3"])
def test_gamma_in_range_is_accepted(hydra_compose, gamma):
    cfg = hydra_compose(f"task.stages.s2.gamma={gamma}")
    task = build_task(cfg)
    assert task.stage_cfg(2).gamma == float(gamma)


def test_valid_variants_build(hydra_compose):
    cfg = hydra_compose(
        "task/gammas=hetero",
        "task.stages.s0.double_dqn=true",
        "task.stages.s1.dueling=true",
        "task.stages.s2.success_threshold=null",
        "task.stages.s3.frames_per_batch=128",
        "task.stages.s3.num_envs=16",
        "logger=none",
    )
    task = build_task(cfg)
    assert task.num_stages == 5
    assert task.stage_names == STAGES
    assert [task.stage_cfg(k).gamma for k in range(5)] == [0.9, 0.9, 0.9, 0.99, 0.9]


# ------------------------------------------------------------------ known package bugs
@pytest.fixture
def no_training(monkeypatch):
    """Makes an experiment fail loudly instead of training if validation lets a config by."""

    def refuse(*args, **kwargs):
        raise AssertionError("training started: the config was not rejected")

    monkeypatch.setattr(BackwardSchedule, "train", refuse)
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_experiment_rejects_threads_zero_with_config_error(hydra_compose, no_training, tmp_path):
    with pytest.raises(ConfigError, match=r"threads=0.*Fix:"):
        Experiment(hydra_compose("threads=0"), tmp_path).run()
    assert not any(tmp_path.iterdir())  # nothing written


def test_threads_default_to_the_tasks_and_an_override_wins(hydra_compose):
    # one thread everywhere: two collapse beside a busy process (scripts/benchmark_threads.py)
    for task in ("gridworld", "manipulator", "cargo"):
        assert hydra_compose(f"task={task}").threads == 1
    assert hydra_compose("task=cargo", "threads=2").threads == 2
    assert hydra_compose("task=manipulator", "task.threads=2").threads == 2


def test_only_stages_whose_values_are_learned_from_check_them(hydra_compose):
    # the manipulator's coarse stage is stage 0: no stage bootstraps from its values
    stages = hydra_compose("task=manipulator").task.stages
    assert stages.coarse.value_tolerance is None and stages.fine.value_tolerance == 0.05
    stages = hydra_compose("experiment=manipulator_td3").task.stages
    assert stages.coarse.value_tolerance is None and stages.fine.value_tolerance == 0.05
    # the grid world's report measures every cell's value, stage 0's included
    assert hydra_compose().task.stages.s0.value_tolerance == 0.01


def test_bad_device_is_reported_on_the_device_key(hydra_compose):
    with pytest.raises(ConfigError) as info:
        build_task(hydra_compose("device=foo"))
    message = str(info.value)
    assert "Fix:" in message
    assert message.startswith("device="), message


@pytest.mark.skipif(torch.cuda.is_available(), reason="the check is for machines without CUDA")
def test_cuda_device_without_cuda_is_reported_before_building_envs(hydra_compose):
    expected = r"^device='cuda': names a CUDA device.*Fix: set device=cpu"
    with pytest.raises(ConfigError, match=expected):
        build_task(hydra_compose("device=cuda"))


@pytest.mark.parametrize(
    ("backend", "module"),
    [("tensorboard", "tensorboard"), ("wandb", "wandb"), ("mlflow", "mlflow")],
)
def test_logger_backend_without_its_package_is_a_config_error(
    hydra_compose, no_training, tmp_path, backend, module
):
    if importlib.util.find_spec(module) is not None:
        pytest.skip(f"{module} is installed")
    with pytest.raises(ConfigError, match=r"logger\.backend.*Fix:"):
        Experiment(hydra_compose(f"logger={backend}"), tmp_path).run()


def test_missing_gpu_index_is_reported_on_the_device_key(hydra_compose, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    expected = r"^device='cuda:3': names a GPU this machine does not have \(it has 1\)\. Fix:"
    with pytest.raises(ConfigError, match=expected):
        build_task(hydra_compose("device=cuda:3"))


# ------------------------------------------------------------------ code that is not found
@pytest.mark.e2e
def test_a_target_that_is_not_importable_names_the_module_and_the_fix(tmp_path):
    broken = tmp_path / "courier_broken.py"
    broken.write_text("import no_such_dependency\n")
    (tmp_path / "courier.py").write_text("class LineEnv:\n    pass\n")
    cases = {
        "task.env._target_=courier_missing.LineEnv": (
            "task.env._target_=courier_missing.LineEnv: module `courier_missing` is not "
            "importable. Fix: add its directory to PYTHONPATH or pip install it"
        ),
        "task.env._target_=courier.LinEnv": "module `courier` has no `LinEnv`. Fix: check",
        "task.env._target_=courier_broken.LineEnv": (
            "module `courier_broken` failed to import (ModuleNotFoundError: No module named "
            "'no_such_dependency')"
        ),
    }
    for override, message in cases.items():
        result = run_cli(
            ["stages-train", "task=custom", override], tmp_path, PYTHONPATH=str(tmp_path)
        )
        assert result.returncode == 2, result.stderr[-2000:]
        assert message in result.stderr, result.stderr[-2000:]
        assert "Traceback" not in result.stderr and "Error locating target" not in result.stderr


def test_stages_by_prefix_refuses_a_value_that_is_not_a_mapping():
    with pytest.raises(ValueError, match=r"takes an id \(a string\), a mapping of id prefixes"):
        by_prefix("MiniGrid-DoorKey-8x8-v0", 0.95, 0.99)
