"""The config layer: schemas with their bounds (:mod:`.schema`), what a composed config becomes
(:mod:`.expansion`), its checks (:mod:`.checks`) and Hydra's registration (:mod:`.registration`)."""

from torchrl_stages.config.bounds import ConfigError, StageChecks, check
from torchrl_stages.config.checks import validate_config
from torchrl_stages.config.expansion import (
    apply_all_stages,
    expand_stage_template,
    stage_keys_set,
    targets,
)
from torchrl_stages.config.registration import register_configs
from torchrl_stages.config.schema import LoggerConfig, StageConfig, TrainConfig, as_dataclass

__all__ = [
    "ConfigError",
    "LoggerConfig",
    "StageChecks",
    "StageConfig",
    "TrainConfig",
    "apply_all_stages",
    "as_dataclass",
    "check",
    "expand_stage_template",
    "register_configs",
    "stage_keys_set",
    "targets",
    "validate_config",
]
