"""PPO, one package: the pure-JAX algorithm (``algorithm``: running statistics, the update as nested
scans, ``make_train``; ``losses``: the estimators and the loss),
per-member views of a population (``members``), the validation suite and best-checkpoint selection
(``selection``), its hooks for the shared training loop (``trainer``), its saved policy (``policy``) and
export (``export``). Importing the package imports only ``algorithm`` and ``losses``."""

from jaxtraffic.learn.ppo.algorithm import PPOConfig, Runner, RunningStats, check_ppo_config, lr_schedule, make_train
from jaxtraffic.learn.ppo.losses import (
    Batch,
    clipped_surrogate,
    compute_gae,
    gaussian_entropy,
    gaussian_log_prob,
    ppo_loss,
)

__all__ = ["Batch", "PPOConfig", "Runner", "RunningStats", "clipped_surrogate", "compute_gae", "gaussian_entropy",
           "gaussian_log_prob", "lr_schedule", "make_train", "ppo_loss", "check_ppo_config"]
