"""Whether a value is known now or only inside a JAX transformation: the one place that asks.

Checks of user input (a controller's gains, an alpha sequence, a plant's parameters) run on concrete
values and are skipped for traced ones (inside ``jit``/``vmap``/``grad``, where the value is not known
and the check must not synchronise with a device). Imports nothing of jaxtraffic: every layer may use it.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

__all__ = ["concrete", "is_traced"]


def is_traced(*trees: Any) -> bool:
    """Whether any leaf of ``trees`` is a tracer (the value is known only when the transformation runs)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(trees))


def concrete(value: Any, *, jax_arrays: bool = True) -> np.ndarray | None:
    """``value`` as a float64 numpy array, or None when it is not known now: a tracer, or with
    ``jax_arrays=False`` any JAX array (reading a device array back synchronises with the device, which can
    deadlock where JAX itself rebuilds a struct around it, e.g. when dispatching ``pmap``), or a value that is
    not numeric (a placeholder leaf)."""
    if isinstance(value, jax.core.Tracer) or (not jax_arrays and isinstance(value, jax.Array)):
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
