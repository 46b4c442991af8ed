"""The training configuration: the config tree (``tree``: plant, env, ppo (``PPOConfig``), grad
(``GradientConfig``), run; config.json and its loader) and the checks every field passes when a tree is built
(``checks``)."""

from jaxtraffic.runs.config.toml import read_config, write_config
from jaxtraffic.runs.config.tree import (
    ALGOS,
    CONFIG_VERSION,
    POPULATION,
    RUN_CONTROL,
    SECTIONS,
    EnvConfig,
    RunConfig,
    TrainConfig,
    config_from_json,
    config_json,
    load_config,
)

__all__ = ["ALGOS", "CONFIG_VERSION", "POPULATION", "RUN_CONTROL", "SECTIONS",
           "EnvConfig", "RunConfig", "TrainConfig",
           "config_from_json", "config_json", "load_config", "read_config", "write_config"]
