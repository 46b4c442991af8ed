"""Named boundary conditions of the ARZ grid (docs/model.md sections 2-3).

Node 0 is the inlet (x = 0), node N the outlet (x = L). Each condition is a small frozen object with
a ``name``; adding one is one more instance here and naming it in ``model.schemes``. They take
arrays only (no parameters object).

* ``INFLOW_DENSITY`` (inlet): the density characteristic enters at x = 0 with the inflow q_in:
  rho_0 = q_in / v_0, v_0 advanced from the interior (its speed difference is the forward one: node 0
  has no left neighbour), and the mass flux through x = 0 is F_{1/2} = rho_0 v_0.
* ``SPEED_ODE`` (outlet): the speed characteristic enters at x = L, so v_N follows the ODE
  v_t = (V - v)/tau_mix (no advection term there); the density leaves with the flux
  F_{N+1/2} = rho_N v_N.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import jax
import jax.numpy as jnp

Array = jax.Array


class Inlet(Protocol):
    """What ``model.solver.rhs`` and ``solver_step`` ask of an inlet condition (see ``InflowDensity``)."""

    @property
    def name(self) -> str: ...  # read-only: the frozen dataclasses' field conforms

    def mass_flux(self, q: Array) -> Array: ...

    def backward_speed_difference(self, vx_fwd: Array) -> Array: ...

    def impose(self, rho: Array, v: Array, q_in: Array | float) -> Array: ...


class Outlet(Protocol):
    """What ``model.solver.rhs`` asks of an outlet condition (see ``SpeedODE``)."""

    @property
    def name(self) -> str: ...  # read-only: the frozen dataclasses' field conforms

    def mass_flux(self, q: Array) -> Array: ...

    def advection(self, dtype: jnp.dtype) -> Array: ...


@dataclasses.dataclass(frozen=True)
class InflowDensity:
    """Inlet: rho_0 = q_in / v_0 (veh/m), with q_in in veh/s and v_0 in m/s."""

    name: str = "inflow_density"

    def mass_flux(self, q: Array) -> Array:
        """F_{1/2} (veh/s), a scalar, from the nodal fluxes q = rho v, shape (n,)."""
        return q[0]

    def backward_speed_difference(self, vx_fwd: Array) -> Array:
        """The speed difference used at node 0 when information comes from the left: the forward
        one (shape (1,), 1/s), from the forward differences of nodes 0..N-1."""
        return vx_fwd[:1]

    def impose(self, rho: Array, v: Array, q_in: Array | float) -> Array:
        """``rho`` with its inlet node set to q_in / v[0]; shape (n,), veh/m."""
        return rho.at[0].set(q_in / v[0])


@dataclasses.dataclass(frozen=True)
class SpeedODE:
    """Outlet: v_N follows v_t = (V - v)/tau_mix; rho_N leaves with its own flux rho_N v_N."""

    name: str = "speed_ode"

    def mass_flux(self, q: Array) -> Array:
        """F_{N+1/2} (veh/s), a scalar, from the nodal fluxes q = rho v, shape (n,)."""
        return q[-1]

    def advection(self, dtype: jnp.dtype) -> Array:
        """The advection term lambda2 v_x at node N: none, shape (1,)."""
        return jnp.zeros((1,), dtype)


INFLOW_DENSITY = InflowDensity()
SPEED_ODE = SpeedODE()
INLETS = {b.name: b for b in (INFLOW_DENSITY,)}
OUTLETS = {b.name: b for b in (SPEED_ODE,)}
