"""How a rollout ended: the divergence codes and an optional host-side check that raises on them.

The traced arrays (``PlantState.diverged_reason``, the metric ``diverged_reason``) hold int32 codes,
the values of ``Divergence``; ``Divergence(code).message`` says what each means, and
``check_outcome`` turns a diverged rollout into an exception for users who prefer one (in the spirit
of a ``throw=`` option) instead of inspecting the flags.
"""

from __future__ import annotations

import enum
from typing import Any

import numpy as np

from jaxtraffic.platform.tracing import is_traced

__all__ = ["Divergence", "DivergedError", "check_outcome"]


class Divergence(enum.IntEnum):
    """Why a plant was frozen (``PlantState.diverged_reason``; docs/model.md section 4).

    NONE (0): healthy. STATE (1): the state left the physical region 0 < rho < 1/l, v >= 0 (or was not
    finite). CONTROL (2): the controller returned a non-finite time gap. INITIAL (3): the initial state
    was not finite or not physical (only reachable with traced inputs; concrete ones are rejected).
    PARAMS (4): traced parameters outside their valid range (``model.params.params_valid``).
    """

    NONE = 0
    STATE = 1
    CONTROL = 2
    INITIAL = 3
    PARAMS = 4

    @property
    def message(self) -> str:
        """A short human-readable description of the outcome."""
        return _MESSAGES[self]


_MESSAGES = {
    Divergence.NONE: "not diverged",
    Divergence.STATE: "state left the physical region",
    Divergence.CONTROL: "controller output not finite",
    Divergence.INITIAL: "initial state not finite or not physical",
    Divergence.PARAMS: "parameters outside their valid range",
}


class DivergedError(RuntimeError):
    """Raised by ``check_outcome`` when a rollout diverged. ``reasons``: the code of every environment
    (a numpy int array, shape () for one rollout or (B,) for a batch)."""

    def __init__(self, message: str, reasons: np.ndarray):
        super().__init__(message)
        self.reasons = reasons


def _reasons_of(result: Any) -> Any:
    metrics = getattr(result, "metrics", result)
    if isinstance(metrics, dict) and "diverged_reason" in metrics:
        return metrics["diverged_reason"]
    final = getattr(result, "final", result)
    if hasattr(final, "diverged_reason"):
        return final.diverged_reason
    raise TypeError(f"check_outcome needs a SimResult, its metrics dict or a PlantState, got {type(result).__name__}")


def check_outcome(result: Any, throw: bool = True) -> list[Divergence]:
    """The outcome of every environment of a rollout, raising if any diverged (when ``throw``).

    Host-side: it reads the codes back from the device, so it does not work under ``jit``/``vmap``
    (a traced result raises ``TypeError``); call it on what ``simulate`` / ``simulate_batch`` return.

    Args:
        result: a ``SimResult`` (of ``simulate`` or ``simulate_batch``), its ``metrics`` dict, or a
            ``PlantState``.
        throw: raise ``DivergedError`` when any environment diverged (default); False only reports.
    Returns:
        The ``Divergence`` of every environment, flattened in batch order (one entry for a single rollout).
    Raises:
        DivergedError: with ``throw``, naming each reason that occurred and the environments it hit.
        TypeError: for a traced result, or an object without divergence codes.
    """
    codes = _reasons_of(result)
    if is_traced(codes):
        raise TypeError("check_outcome reads the codes on the host: it cannot run under jit/vmap")
    arr = np.asarray(codes)
    outcomes = [Divergence(int(c)) for c in arr.reshape(-1)]
    if throw and any(outcomes):
        parts = []
        for reason in sorted({o for o in outcomes if o}):
            where = [i for i, o in enumerate(outcomes) if o == reason]
            envs = "" if arr.ndim == 0 else f" (environment(s) {where})"
            parts.append(f"{reason.name}: {reason.message}{envs}")
        raise DivergedError("rollout diverged: " + "; ".join(parts), arr)
    return outcomes
