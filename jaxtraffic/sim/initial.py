"""Initial conditions (docs/model.md section 5): the paper's cosine perturbation and the equilibrium."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxtraffic.model.params import TrafficParams, equilibrium

Array = jax.Array


def paper_initial_condition(
    p: TrafficParams, amplitude: float | Array = 0.010, wavenumber: float | Array = 4.0,
    phase: float | Array = 0.0, dtype: Any = jnp.float32, rho_bar: Array | None = None,
) -> tuple[Array, Array]:
    """Initial state of docs/model.md section 5 (shapes (n_points,)).

    rho(x, 0) = rho_bar + amplitude cos(2 pi wavenumber x / L + phase) (amplitude in veh/m; the
    paper's: 10 veh/km, wavenumber 4), v(x, 0) = q_in / rho(x, 0). ``rho_bar``: the equilibrium
    density of ``p`` (veh/m) if the caller has it already (default: computed).
    """
    rho_bar = equilibrium(p)[0] if rho_bar is None else rho_bar
    x = p.x()
    rho0 = rho_bar + amplitude * jnp.cos(2.0 * jnp.pi * wavenumber * x / p.L + phase)
    rho0 = rho0.astype(dtype)
    return rho0, (p.q_in / rho0).astype(dtype)


def equilibrium_state(p: TrafficParams, dtype: Any = jnp.float32) -> tuple[Array, Array]:
    """The uniform equilibrium fields (rho_bar, v_bar), shapes (n_points,)."""
    rho_bar, v_bar = equilibrium(p)
    return jnp.full((p.n_points,), rho_bar, dtype), jnp.full((p.n_points,), v_bar, dtype)

