"""``train_run(config)``: train the run a ``TrainConfig`` describes, with its algorithm (``config.run.algo``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from jaxtraffic.runs.config import TrainConfig


def train_run(config: TrainConfig, callbacks: Sequence[Callable[[dict], None]] = ()) -> Path:
    """Train ``config`` (PPO or the gradient trainer, by ``config.run.algo``) and return its run directory;
    ``callbacks``: each learning-curve row."""
    if config.run.algo == "gradient":
        from jaxtraffic.runs.gradient.trainer import train_gradient

        return train_gradient(config, callbacks)
    from jaxtraffic.runs.ppo.trainer import train

    return train(config, callbacks)
