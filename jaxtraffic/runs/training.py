"""``train_run(config)``: train (or resume) the run a ``TrainConfig`` describes, whatever its algorithm."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from jaxtraffic.runs.config import TrainConfig


def train_run(config: TrainConfig, callbacks: Sequence[Callable[[dict], None]] = ()) -> Path:
    """Train ``config`` (``config.run.algo``: PPO, or gradient / CEM training) into ``config.run.out_dir`` and
    return the run directory; ``callbacks`` receive each learning-curve row. Raises ``TrainingInterrupted`` after
    SIGINT / SIGTERM (the last checkpoint is on disk; ``config.replace(resume=True)`` continues it)."""
    if config.run.algo == "gradient":
        from jaxtraffic.runs.gradient.trainer import train_gradient

        return train_gradient(config, callbacks)
    from jaxtraffic.runs.ppo.trainer import train

    return train(config, callbacks)
