"""The training configuration: the config tree (``tree``: plant, env, ppo (``PPOConfig``), grad
(``GradientConfig``), run), the run's config files (``toml``: config.toml, its truth, config.json, the machine
copy, and their loader) and the checks every field passes when a tree is built (``checks``)."""

from jaxtraffic.runs.config.toml import config_from_json, config_json, load_config, read_config, write_config
from jaxtraffic.runs.config.tree import (
    ALGOS,
    CONFIG_VERSION,
    POPULATION,
    RUN_CONTROL,
    SECTIONS,
    EnvConfig,
    RunConfig,
    TrainConfig,
)

__all__ = ["ALGOS", "CONFIG_VERSION", "POPULATION", "RUN_CONTROL", "SECTIONS",
           "EnvConfig", "RunConfig", "TrainConfig",
           "config_from_json", "config_json", "load_config", "read_config", "write_config"]
