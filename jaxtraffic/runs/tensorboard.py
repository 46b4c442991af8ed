"""Optional metrics writers, fed the learning-curve rows of both trainers (PPO's callback hook, the gradient
trainer's chunks).

``TensorBoardWriter(logdir)`` writes every numeric field of a row as a scalar ``train/<field>``
against ``env_steps`` (tensorboardX, ``pip install 'jaxtraffic[tb]'``; ``jaxtraffic-train
--tensorboard DIR``). View with ``tensorboard --logdir DIR`` (the viewer is in the ``[tb]`` extra too).

A resumed run continues from its checkpoint, which may be older than the last rows the interrupted session
logged: ``purge_step`` (the first step the new session logs; ``run_training`` passes the checkpoint's
env_steps + 1) makes TensorBoard drop the old session's events from that step on, so a step is not drawn twice.
"""

from __future__ import annotations

import math
from pathlib import Path


class TensorBoardWriter:
    """A training callback writing the learning-curve rows as TensorBoard scalars."""

    def __init__(self, logdir: str | Path, purge_step: int | None = None):
        try:
            from tensorboardX import SummaryWriter
        except ImportError as err:
            raise ValueError("--tensorboard needs tensorboardX: pip install 'jaxtraffic[tb]'") from err
        self.logdir = Path(logdir)
        self._writer = SummaryWriter(str(self.logdir), purge_step=purge_step)

    def __call__(self, row: dict) -> None:
        step = int(row["env_steps"])
        for name, value in row.items():
            if name != "env_steps" and isinstance(value, (int, float)) and math.isfinite(value):
                self._writer.add_scalar(f"train/{name}", value, step)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()
