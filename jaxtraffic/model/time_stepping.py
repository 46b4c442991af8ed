"""Explicit time integrators as data: a few numbers driving one generic stepper.

A ``ShuOsherTableau`` describes an explicit Runge-Kutta method in a Shu-Osher (convex combination)
form where every stage is

    u^(i) = w_i * (u^(k_1) + ... + u^(k_m) + dt L(u^(i-1))),      u^(0) = u,

with the sources k_1 < ... < k_m < i taken from ``sources[i-1]`` and w_i = ``weights[i-1]`` (None:
no multiplication). The boundary conditions are imposed after every stage (``impose``). The mass
fluxes reported for the step are the sum of the stages' right-hand-side fluxes times
``flux_weight`` (None: no multiplication), i.e. their average when all stages weigh the same.

The additions are made in the order written above, left to right, so that the floating-point
operations are exactly those of the hand-written methods the tableau replaces:
forward Euler ``u + dt L(u)`` and Heun ``0.5 (u + u1 + dt L(u1))``.
Adding an integrator of this form is one more instance here and one entry in ``model.schemes``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax

Array = jax.Array
# a right-hand side: state -> (time derivative of the state, (F_in, F_out))
RHS = Callable[[Any], tuple[Any, tuple[Array, Array]]]


@dataclasses.dataclass(frozen=True)
class ShuOsherTableau:
    """An explicit method of the form of the module docstring.

    Attributes:
        name: a label.
        sources: per stage i = 1..s, the indices (< i, increasing) of the earlier stages summed.
        weights: per stage, the factor w_i applied to the sum, or None for none.
        flux_weight: the factor applied to the sum of the stages' boundary fluxes, or None.
    Raises:
        ValueError: on construction, if the lengths differ or a stage reads a stage not yet computed.
    """

    name: str
    sources: tuple[tuple[int, ...], ...]
    weights: tuple[float | None, ...]
    flux_weight: float | None

    def __post_init__(self) -> None:
        if len(self.sources) != len(self.weights) or not self.sources:
            raise ValueError(f"{self.name}: need one weight per stage and at least one stage")
        for i, src in enumerate(self.sources, start=1):
            if not src or any(not 0 <= k < i for k in src) or list(src) != sorted(set(src)):
                raise ValueError(f"{self.name}: stage {i} must sum increasing earlier stages, got {src}")

    @property
    def n_stages(self) -> int:
        """Number of right-hand-side evaluations per step."""
        return len(self.sources)


FORWARD_EULER = ShuOsherTableau("forward_euler", sources=((0,),), weights=(None,), flux_weight=None)
"""u_new = u + dt L(u): first order."""

SSP_RK2 = ShuOsherTableau("ssp_rk2", sources=((0,), (0, 1)), weights=(None, 0.5), flux_weight=0.5)
"""Heun / SSP-RK2: u1 = u + dt L(u), u_new = (u + u1 + dt L(u1)) / 2: second order, TVD under CFL <= 1."""


def _add(a: Any, b: Any) -> Any:
    return jax.tree.map(lambda x, y: x + y, a, b)


def _scale(w: float | None, a: Any) -> Any:
    return a if w is None else jax.tree.map(lambda x: w * x, a)


def rk_step(tableau: ShuOsherTableau, rhs: RHS, impose: Callable[[Any], Any], u: Any, dt: Array | float
            ) -> tuple[Any, tuple[Array, Array]]:
    """One step of length ``dt`` of ``tableau`` on the state ``u`` (a pytree, e.g. (rho, v)).

    Args:
        tableau: the method.
        rhs: u -> (du/dt, (F_in, F_out)), du/dt a pytree like u (units of u per s), F the boundary
            mass fluxes (veh/s).
        impose: the boundary conditions, u -> u, applied after every stage.
        u: the state at t.
        dt: step length, s.
    Returns:
        (u at t + dt, (F_in, F_out) of the step per ``tableau.flux_weight``).
    """
    stages = [u]
    f_in = f_out = None
    for src, w in zip(tableau.sources, tableau.weights, strict=True):
        du, (fi, fo) = rhs(stages[-1])
        f_in = fi if f_in is None else f_in + fi
        f_out = fo if f_out is None else f_out + fo
        acc = stages[src[0]]
        for k in src[1:]:
            acc = _add(acc, stages[k])
        acc = jax.tree.map(lambda x, d: x + dt * d, acc, du)
        stages.append(impose(_scale(w, acc)))
    assert f_in is not None and f_out is not None  # (a tableau has at least one stage)
    if tableau.flux_weight is not None:
        f_in, f_out = tableau.flux_weight * f_in, tableau.flux_weight * f_out
    return stages[-1], (f_in, f_out)
