"""Spatial discretisations of the ARZ right-hand side: how the interior fluxes and speed differences
are reconstructed from the nodal fields (docs/model.md section 3).

A ``Reconstruction`` is data: a name and two pure functions of arrays (no parameters object), so that
adding a discretisation is one more instance here and one more entry in ``model.schemes``:

* ``face_fluxes(q)``: the mass fluxes F_{i+1/2} (veh/s) at the interior faces i = 1..N-1 from the
  nodal fluxes q = rho v, shape (n,) -> (n - 2,). The fluxes through x = 0 and x = L are the
  boundary conditions' (``model.boundary``).
* ``speed_differences(v, inv_dx)``: (vx_fwd, vx_bwd), the one-sided speed differences (1/s) with
  information from the right at nodes 0..N-1 and from the left at nodes 1..N, shapes (n - 1,) each.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp

Array = jax.Array


def minmod(a: Array, b: Array) -> Array:
    """Minmod limiter: the smaller-magnitude argument if both have the same sign, else 0.

    Args:
        a: an array (any units).
        b: an array of the shape and units of ``a``.
    Returns:
        The limited value, elementwise, shape and units of ``a``.
    """
    return jnp.where(a * b > 0, jnp.sign(a) * jnp.minimum(jnp.abs(a), jnp.abs(b)), 0.0)


def limited_slopes(u: Array) -> Array:
    """Minmod slopes per cell of the nodal field ``u``, shape (n,) -> (n,), in units of u.

    Zero at both end nodes (no neighbour on one side); minmod of the two one-sided differences at
    nodes 1..N-1.
    """
    d = jnp.diff(u)
    inner = minmod(d[:-1], d[1:])
    z = jnp.zeros((1,), u.dtype)
    return jnp.concatenate([z, inner, z])


@dataclasses.dataclass(frozen=True)
class Reconstruction:
    """A spatial discretisation (see the module docstring for the two functions' contracts)."""

    name: str
    face_fluxes: Callable[[Array], Array]
    speed_differences: Callable[[Array, Array | float], tuple[Array, Array]]


def _upwind_faces(q: Array) -> Array:
    return q[1:-1]  # F_{i+1/2} = q_i: the upwind node for v > 0


def _upwind_speed_differences(v: Array, inv_dx: Array | float) -> tuple[Array, Array]:
    vx = (v[1:] - v[:-1]) * inv_dx
    return vx, vx


def _muscl_faces(q: Array) -> Array:
    sq = limited_slopes(q)
    return q[1:-1] + 0.5 * sq[1:-1]  # upwind (v > 0) piecewise-linear value at the face i+1/2


def _muscl_speed_differences(v: Array, inv_dx: Array | float) -> tuple[Array, Array]:
    s = limited_slopes(v)
    right = v - 0.5 * s  # value at face i-1/2 seen from node i
    left = v + 0.5 * s  # value at face i+1/2 seen from node i
    vx_fwd = (right[1:] - right[:-1]) * inv_dx  # information from the right, nodes 0..N-1
    vx_bwd = (left[1:] - left[:-1]) * inv_dx  # information from the left, nodes 1..N
    return vx_fwd, vx_bwd


FIRST_ORDER_UPWIND = Reconstruction("first_order_upwind", _upwind_faces, _upwind_speed_differences)
"""Piecewise-constant states: first-order upwind fluxes and differences (the paper's method)."""

MUSCL_MINMOD = Reconstruction("muscl_minmod", _muscl_faces, _muscl_speed_differences)
"""Minmod-limited piecewise-linear reconstruction of the flux and of v: second order where smooth."""
