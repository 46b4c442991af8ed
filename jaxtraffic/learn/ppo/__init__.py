"""PPO, one package: the pure-JAX algorithm (``algorithm``: losses, GAE, running statistics, ``make_train``),
per-member views of a population (``members``), the validation suite and best-checkpoint selection
(``selection``), its hooks for the shared training loop (``trainer``), its saved policy (``policy``) and
export (``export``). Importing the package imports only ``algorithm``."""

from jaxtraffic.learn.ppo.algorithm import (
    PPOConfig,
    Runner,
    RunningStats,
    clipped_surrogate,
    compute_gae,
    gaussian_entropy,
    gaussian_log_prob,
    lr_schedule,
    make_train,
    ppo_loss,
    validate_config,
)

__all__ = ["PPOConfig", "Runner", "RunningStats", "clipped_surrogate", "compute_gae", "gaussian_entropy",
           "gaussian_log_prob", "lr_schedule", "make_train", "ppo_loss", "validate_config"]
