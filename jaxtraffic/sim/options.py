"""Rollout options grouped into small frozen objects (``simulate`` / ``simulate_batch``).

* ``Record``: what is recorded while the rollout streams (the trajectory's stride).
* ``Memory``: how the rollout trades memory for time (checkpointing for reverse mode, batch chunks).
* ``AlphaInput``: where the plant's penetration rate of every step comes from (a drawn noise
  reading, or a given sequence) and whether the controller sees it.

``Record`` and ``Memory`` are static (hashable; a change compiles a new program). ``AlphaInput`` is a
pytree: its ``alphas`` are traced data, its ``noise`` reading is static.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import cast

import jax
from flax import struct

from jaxtraffic.sim.plant import NoiseReading

Array = jax.Array

__all__ = ["AlphaInput", "Memory", "Record"]


def _is_int(x: object) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


@dataclasses.dataclass(frozen=True)
class Record:
    """Recording of a rollout (static).

    Attributes:
        every: record the fields every k-th step from t = 0 into ``SimResult.trajectory`` (0: no
            trajectory, metrics only). ``n_steps`` must be a multiple of it.
    Raises:
        ValueError: on construction, unless ``every`` is an int >= 0.
    """

    every: int = 0

    def __post_init__(self) -> None:
        if not _is_int(self.every) or self.every < 0:
            raise ValueError(f"record_every must be an int >= 0 (0: no trajectory), got {self.every!r}")
        object.__setattr__(self, "every", int(self.every))


@dataclasses.dataclass(frozen=True)
class Memory:
    """Memory/time trade-offs of a rollout (static); none changes the values.

    Attributes:
        remat: checkpoint every recording chunk (``jax.checkpoint``) for reverse-mode
            differentiation, so that the memory of a gradient grows with n_steps / every + every
            steps instead of n_steps. Needs ``Record(every > 0)`` (the chunk length).
        chunk_size: ``simulate_batch`` only: a batch larger than this runs as a sequential loop over
            chunks of ``chunk_size`` environments, each vmapped over the whole rollout (``None`` or 0:
            one vmap over everything; "auto", the default: ``CPU_CHUNK`` on a CPU, one vmap on an
            accelerator, ``chunk_for``). Results do not depend on it beyond rounding.
    Raises:
        ValueError: on construction, unless ``chunk_size`` is None, "auto" or an int >= 0.
    """

    remat: bool = False
    chunk_size: int | str | None = "auto"

    def __post_init__(self) -> None:
        c = self.chunk_size
        if c is not None and c != "auto" and (not _is_int(c) or int(cast(int, c)) < 0):
            raise ValueError(f"chunk_size must be None or an int >= 0 (or 'auto'), got {c!r}")

    def chunk_for(self, platform: str) -> int:
        """The chunk size in effect on devices of ``platform`` ("cpu", "gpu", "tpu", ...; 0: one vmap)."""
        if self.chunk_size == "auto":
            return CPU_CHUNK if platform == "cpu" else 0
        return int(self.chunk_size or 0)


CPU_CHUNK = 64  # environments per sequential chunk of a large batch on a CPU (Memory's "auto")


@struct.dataclass
class AlphaInput:
    """The plant's penetration rate of every step.

    Attributes:
        alphas: the plant's alpha at every step instead of a draw (traced), shape (n_steps,) or
            (n_steps, n_points) per node for ``simulate``, with a leading batch axis (B, ...) for
            ``simulate_batch``; values in [0, 1]. ``sim.rollout.plant_alphas`` gives the draw of a key
            and reading. None (default): drawn from the key.
        noise: how the alpha noise is drawn and whether the controller sees it (``NoiseReading``,
            static; None: one road-wide draw per step, plant only). With ``alphas`` given it may
            only say whether the controller sees them (``model_sees``).
    """

    alphas: Array | None = None
    noise: NoiseReading | None = struct.field(pytree_node=False, default=None)
