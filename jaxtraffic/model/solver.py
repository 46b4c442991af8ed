"""Explicit finite-volume step of the nonlinear ARZ model (docs/model.md sections 2-3).

Grid: ``n_points`` nodes x_i = i dx, i = 0..N. Node 0 is the inlet, where the density
characteristic enters: rho_0 = q_in / v_0 with v_0 advanced from the interior. Nodes 1..N carry
the density as cell averages updated in flux form,

    rho_i <- rho_i - dt/dx (F_{i+1/2} - F_{i-1/2}),  F_{1/2} = rho_0 v_0 = q_in,  F_{N+1/2} = rho_N v_N,

so the discrete mass M = dx * sum_{i=1..N} rho_i changes by exactly (F_in - F_out) dt, to
rounding. The speed obeys the non-conservative equation v_t + lambda2 v_x = (V - v)/tau_mix,
upwinded by the sign of lambda2 = v - 1/(rho h_mix); at x = L it follows the outlet ODE
v_t = (V - v)/tau_mix, where the speed characteristic enters.

Schemes (static ``params.scheme``):
  * ``"upwind"``: first-order upwind fluxes and differences, forward Euler (the paper's method).
  * ``"muscl"``: minmod-limited piecewise-linear reconstruction of fluxes and of v, with
    SSP-RK2 (Heun) time stepping; second order where the solution is smooth.
Both keep the uniform equilibrium (rho_bar, v_bar, h_bar) as a fixed point.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from jaxtraffic.model import fundamental as fd
from jaxtraffic.model.params import TrafficParams

Array = jax.Array


def minmod(a: Array, b: Array) -> Array:
    """Minmod limiter: the smaller-magnitude argument if both have the same sign, else 0."""
    return jnp.where(a * b > 0, jnp.sign(a) * jnp.minimum(jnp.abs(a), jnp.abs(b)), 0.0)


def _limited_slopes(u: Array) -> Array:
    """Minmod slopes (per cell, in units of u) at nodes 1..N-1; zero at both end nodes."""
    d = jnp.diff(u)
    inner = minmod(d[:-1], d[1:])
    z = jnp.zeros((1,), u.dtype)
    return jnp.concatenate([z, inner, z])


def _speeds_and_source(rho: Array, v: Array, h: Array, alpha: Array, p: TrafficParams):
    """(lambda2, (V(rho, h) - v) / tau_mix) at every node, with two divisions per node.

    Same quantities as ``fundamental.characteristic_speeds`` / ``fundamental.V`` (equal up to
    rounding): 1/h_mix(h) = (alpha + b h) / (c h) and 1/tau_mix = alpha/tau_acc + (1-alpha)/tau_m.
    """
    c, b = fd.mix_coefficients(p, alpha)
    inv_tau = alpha / p.tau_acc + (1.0 - alpha) / p.tau_m
    inv_rho = 1.0 / rho
    inv_hm = (alpha + b * h) / (c * h)
    lam2 = v - inv_rho * inv_hm
    source = ((inv_rho - p.l) * inv_hm - v) * inv_tau
    return lam2, source


def _rhs(rho: Array, v: Array, h: Array, alpha: Array, p: TrafficParams, second_order: bool):
    """Semi-discrete right-hand side.

    Returns (drho_dt, dv_dt, F_in, F_out) with drho_dt zero at the inlet node (set by the
    boundary condition) and F_in / F_out the mass fluxes (veh/s) through x = 0 and x = L.
    """
    inv_dx = 1.0 / p.dx
    q = rho * v
    if second_order:
        sq = _limited_slopes(q)
        face = q[1:-1] + 0.5 * sq[1:-1]  # F_{i+1/2}, i = 1..N-1, upwind (v > 0) reconstruction
    else:
        face = q[1:-1]
    f_in, f_out = q[0], q[-1]
    flux = jnp.concatenate([f_in[None], face, f_out[None]])  # F_{1/2} .. F_{N+1/2}
    drho = jnp.concatenate([jnp.zeros((1,), rho.dtype), (flux[:-1] - flux[1:]) * inv_dx])

    lam2, source = _speeds_and_source(rho, v, h, alpha, p)
    if second_order:
        s = _limited_slopes(v)
        right = v - 0.5 * s  # value at face i-1/2 seen from node i
        left = v + 0.5 * s  # value at face i+1/2 seen from node i
        vx_fwd = (right[1:] - right[:-1]) * inv_dx  # information from the right, nodes 0..N-1
        vx_bwd = (left[1:] - left[:-1]) * inv_dx  # information from the left, nodes 1..N
    else:
        vx_fwd = (v[1:] - v[:-1]) * inv_dx
        vx_bwd = vx_fwd
    # node 0 has no left neighbour: forward difference there; node N follows the outlet ODE
    vx_b = jnp.concatenate([vx_fwd[:1], vx_bwd[:-1]])  # backward differences at nodes 0..N-1
    vx = jnp.where(lam2[:-1] < 0, vx_fwd, vx_b)
    adv = jnp.concatenate([lam2[:-1] * vx, jnp.zeros((1,), v.dtype)])
    dv = source - adv
    return drho, dv, f_in, f_out


def _apply_inlet(rho: Array, v: Array, p: TrafficParams) -> Array:
    """Inlet boundary condition rho_0 = q_in / v_0."""
    return rho.at[0].set(p.q_in / v[0])


def _solver_step(rho: Array, v: Array, h: Array, alpha: Array, p: TrafficParams, dt: Array | float
                 ) -> tuple[Array, Array, Array, Array]:
    """One explicit step of length ``dt`` of ``p.scheme``; returns (rho, v, F_in, F_out)."""
    if p.scheme == "upwind":
        drho, dv, f_in, f_out = _rhs(rho, v, h, alpha, p, second_order=False)
        rho1, v1 = rho + dt * drho, v + dt * dv
        return _apply_inlet(rho1, v1, p), v1, f_in, f_out
    # SSP-RK2: u1 = u + dt L(u); u_new = (u + u1 + dt L(u1)) / 2
    drho, dv, f_in0, f_out0 = _rhs(rho, v, h, alpha, p, second_order=True)
    rho1, v1 = rho + dt * drho, v + dt * dv
    rho1 = _apply_inlet(rho1, v1, p)
    drho1, dv1, f_in1, f_out1 = _rhs(rho1, v1, h, alpha, p, second_order=True)
    rho2 = 0.5 * (rho + rho1 + dt * drho1)
    v2 = 0.5 * (v + v1 + dt * dv1)
    return _apply_inlet(rho2, v2, p), v2, 0.5 * (f_in0 + f_in1), 0.5 * (f_out0 + f_out1)


def arz_step(
    rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None
) -> tuple[Array, Array, Array, Array]:
    """Advance (rho in veh/m, v in m/s) by one step dt under the applied time gap ``h`` (s), held
    over the step, in ``p.substeps`` solver steps of dt / substeps.

    Args:
        rho, v, h: fields of shape (n_points,).
        p: parameters (scheme, dx, dt, substeps, physical constants).
        alpha: plant penetration rate for this step (defaults to ``p.alpha``).
    Returns:
        (rho_new, v_new, F_in, F_out): the new state and the time-averaged mass fluxes (veh/s)
        through the inlet and the outlet during the step, so that
        dx * sum(rho_new[1:]) - dx * sum(rho[1:]) = (F_in - F_out) dt.
    """
    chex.assert_rank([rho, v, h], 1)
    chex.assert_equal_shape([rho, v, h])
    a = p.alpha if alpha is None else alpha
    if p.substeps == 1:
        return _solver_step(rho, v, h, a, p, p.dt)
    dt = p.solver_dt

    def body(_, carry):
        r, u, f_in, f_out = carry
        r, u, fi, fo = _solver_step(r, u, h, a, p, dt)
        return r, u, f_in + fi, f_out + fo

    zero = jnp.zeros((), rho.dtype)
    r, u, f_in, f_out = jax.lax.fori_loop(0, p.substeps, body, (rho, v, zero, zero))
    return r, u, f_in / p.substeps, f_out / p.substeps


def is_physical(rho: Array, v: Array, p: TrafficParams) -> Array:
    """True when the state is finite and in the physical region 0 < rho < 1/l, 0 <= v < inf.

    One fused reduction: a NaN fails every comparison, an infinite rho fails rho < 1/l.
    """
    return jnp.all(fd.in_physical_region(rho, v, p.l))


def local_cfl(rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None) -> Array:
    """CFL number max(|lambda1|, |lambda2|) dt_s/dx at every node for the current state (dt_s: the
    solver step dt / substeps)."""
    lam2, _ = _speeds_and_source(rho, v, h, p.alpha if alpha is None else alpha, p)
    return jnp.maximum(jnp.abs(v), jnp.abs(lam2)) * (p.solver_dt / p.dx)


def max_cfl(rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None) -> Array:
    """Largest CFL number max_i |lambda_k| dt/dx over the grid for the current state."""
    return jnp.max(local_cfl(rho, v, h, p, alpha))
