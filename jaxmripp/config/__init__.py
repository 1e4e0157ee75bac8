"""Typed, frozen, validated configuration.

Every section is a frozen dataclass, so a whole `Config` is hashable and can be passed to
`jax.jit` as a static argument. YAML files and dotted command-line overrides
(`world.size=64`) are merged into the defaults and validated once, on load: a bad value
raises `ConfigError` with one line naming the key, the value and what is allowed.

Modules: `sections` (the dataclasses and their defaults), `rules` (allowed values and
`validate`), `loading` (YAML presets, overrides, conversion to plain data), `presets`
(the presets packaged in jaxmripp/configs, by name), `cli` (the entry points' error
convention), `errors`.
"""

from jaxmripp.config.errors import ConfigError
from jaxmripp.config.loading import REMOVED, from_dict, load, parse_override, to_dict, to_yaml
from jaxmripp.config.rules import METRIC_SINKS, PLANNERS, REFERENCES, RULES, validate
from jaxmripp.config.sections import (
    REFERENCE_SIZE,
    CandidateConfig,
    Config,
    EpisodeConfig,
    EvalConfig,
    GPConfig,
    PolicyConfig,
    PPOConfig,
    RadioConfig,
    RewardConfig,
    RobotConfig,
    SafetyConfig,
    SensorConfig,
    TrainConfig,
    WorldConfig,
)

__all__ = [
    "METRIC_SINKS",
    "PLANNERS",
    "REFERENCES",
    "REFERENCE_SIZE",
    "REMOVED",
    "RULES",
    "CandidateConfig",
    "Config",
    "ConfigError",
    "EpisodeConfig",
    "EvalConfig",
    "GPConfig",
    "PPOConfig",
    "PolicyConfig",
    "RadioConfig",
    "RewardConfig",
    "RobotConfig",
    "SafetyConfig",
    "SensorConfig",
    "TrainConfig",
    "WorldConfig",
    "from_dict",
    "load",
    "parse_override",
    "to_dict",
    "to_yaml",
    "validate",
]
