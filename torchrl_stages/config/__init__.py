"""The config layer: schemas with their bounds (:mod:`.schema`), what a composed config becomes
(:mod:`.expansion`), its checks (:mod:`.checks`) and Hydra's registration (:mod:`.registration`)."""

from torchrl_stages.config.checks import (
    TargetError,
    check_env_keys,
    missing_keys,
    validate_config,
    validate_sweeper,
    validate_task,
)
from torchrl_stages.config.expansion import (
    apply_all_stages,
    expand_stage_template,
    stage_keys_set,
    targets,
)
from torchrl_stages.config.registration import config_group_options, register_configs
from torchrl_stages.config.schema import (
    ConfigError,
    EvalConfig,
    LoggerConfig,
    ObjectiveConfig,
    ScheduleConfig,
    StageChecks,
    StageConfig,
    TaskConfig,
    TrainConfig,
    TuneConfig,
    as_dataclass,
    check,
    objective_value,
)

__all__ = [
    "ConfigError",
    "EvalConfig",
    "LoggerConfig",
    "ObjectiveConfig",
    "ScheduleConfig",
    "StageChecks",
    "StageConfig",
    "TargetError",
    "TaskConfig",
    "TrainConfig",
    "TuneConfig",
    "apply_all_stages",
    "as_dataclass",
    "check",
    "check_env_keys",
    "config_group_options",
    "expand_stage_template",
    "missing_keys",
    "objective_value",
    "register_configs",
    "stage_keys_set",
    "targets",
    "validate_config",
    "validate_sweeper",
    "validate_task",
]
