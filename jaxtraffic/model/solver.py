"""Explicit finite-volume step of the nonlinear ARZ model (docs/model.md sections 2-3).

Grid: ``n_points`` nodes x_i = i dx, i = 0..N. Node 0 is the inlet, where the density
characteristic enters: rho_0 = q_in / v_0 with v_0 advanced from the interior. Nodes 1..N carry
the density as cell averages updated in flux form,

    rho_i <- rho_i - dt/dx (F_{i+1/2} - F_{i-1/2}),  F_{1/2} = rho_0 v_0 = q_in,  F_{N+1/2} = rho_N v_N,

so the discrete mass M = dx * sum_{i=1..N} rho_i changes by exactly (F_in - F_out) dt, to
rounding. The speed obeys the non-conservative equation v_t + lambda2 v_x = (V - v)/tau_mix,
upwinded by the sign of lambda2 = v - 1/(rho h_mix); at x = L it follows the outlet ODE
v_t = (V - v)/tau_mix, where the speed characteristic enters.

Schemes (static ``params.scheme``, looked up in ``model.schemes.SCHEMES``) are composed of
separate pieces: a spatial discretisation (``model.reconstruction``), an explicit time integrator
(``model.time_stepping``) and named boundary conditions (``model.boundary``):
  * ``"upwind"``: first-order upwind fluxes and differences, forward Euler (the paper's method).
  * ``"muscl"``: minmod-limited piecewise-linear reconstruction of fluxes and of v, with
    SSP-RK2 (Heun) time stepping; second order where the solution is smooth.
Both keep the uniform equilibrium (rho_bar, v_bar, h_bar) as a fixed point. This module holds the
physics (characteristic speed, relaxation source) and assembles the pieces.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from jaxtraffic.model import fundamental
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.model.reconstruction import minmod
from jaxtraffic.model.schemes import Scheme, get_scheme
from jaxtraffic.model.time_stepping import rk_step

Array = jax.Array

__all__ = ["arz_step", "is_physical", "local_cfl", "max_cfl", "minmod", "rhs", "solver_step"]


def _speeds_and_source(rho: Array, v: Array, h: Array, alpha: Array | float, p: TrafficParams):
    """(lambda2, (V(rho, h) - v) / tau_mix) at every node, with two divisions per node.

    Same quantities as ``fundamental.characteristic_speeds`` / ``fundamental.V`` (equal up to
    rounding): 1/h_mix(h) = (alpha + b h) / (c h) and 1/tau_mix = alpha/tau_acc + (1-alpha)/tau_m.
    """
    c, b = fundamental.mix_coefficients(p, alpha)
    inv_tau = alpha / p.tau_acc + (1.0 - alpha) / p.tau_m
    inv_rho = 1.0 / rho
    inv_hm = (alpha + b * h) / (c * h)
    lam2 = v - inv_rho * inv_hm
    source = ((inv_rho - p.l) * inv_hm - v) * inv_tau
    return lam2, source


def rhs(rho: Array, v: Array, h: Array, alpha: Array | float, p: TrafficParams, scheme: Scheme
        ) -> tuple[tuple[Array, Array], tuple[Array, Array]]:
    """Semi-discrete right-hand side of ``scheme``'s spatial discretisation and boundary conditions.

    Args:
        rho: density (veh/m), shape (n_points,).
        v: speed (m/s), shape (n_points,).
        h: applied time gap (s), shape (n_points,).
        alpha: plant penetration rate (scalar or per node).
        p: parameters (dx and the physical constants).
        scheme: the composed scheme (``model.schemes.get_scheme``).
    Returns:
        ((drho_dt, dv_dt), (F_in, F_out)): the time derivatives, shapes (n_points,) in veh/(m s) and
        m/s^2 (drho_dt is zero at the inlet node, whose density the inlet condition sets), and the
        scalar mass fluxes (veh/s) through x = 0 and x = L.
    """
    inv_dx = 1.0 / p.dx
    q = rho * v
    f_in, f_out = scheme.inlet.mass_flux(q), scheme.outlet.mass_flux(q)
    flux = jnp.concatenate([f_in[None], scheme.reconstruction.face_fluxes(q), f_out[None]])  # F_{1/2}..F_{N+1/2}
    drho = jnp.concatenate([jnp.zeros((1,), rho.dtype), (flux[:-1] - flux[1:]) * inv_dx])

    lam2, source = _speeds_and_source(rho, v, h, alpha, p)
    vx_fwd, vx_bwd = scheme.reconstruction.speed_differences(v, inv_dx)
    vx_b = jnp.concatenate([scheme.inlet.backward_speed_difference(vx_fwd), vx_bwd[:-1]])  # nodes 0..N-1
    vx = jnp.where(lam2[:-1] < 0, vx_fwd, vx_b)  # upwinded by the sign of lambda2
    adv = jnp.concatenate([lam2[:-1] * vx, scheme.outlet.advection(v.dtype)])
    dv = source - adv
    return (drho, dv), (f_in, f_out)


def solver_step(rho: Array, v: Array, h: Array, alpha: Array | float, p: TrafficParams, dt: Array | float,
                scheme: Scheme | None = None) -> tuple[Array, Array, Array, Array]:
    """One explicit step of length ``dt`` (s) of ``scheme`` (default: ``get_scheme(p.scheme)``).

    Args: as ``rhs``, plus the step ``dt``.
    Returns:
        (rho, v, F_in, F_out): the new fields (shapes (n_points,)) and the boundary mass fluxes of the
        step (veh/s, weighted over the stages by the integrator).
    Raises:
        ValueError: for an unknown ``p.scheme``.
    """
    scheme = get_scheme(p.scheme) if scheme is None else scheme
    inlet = scheme.inlet

    def stage_rhs(u):
        return rhs(u[0], u[1], h, alpha, p, scheme)

    def impose(u):
        return inlet.impose(u[0], u[1], p.q_in), u[1]

    (rho_new, v_new), (f_in, f_out) = rk_step(scheme.integrator, stage_rhs, impose, (rho, v), dt)
    return rho_new, v_new, f_in, f_out


def arz_step(
    rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None
) -> tuple[Array, Array, Array, Array]:
    """Advance (rho in veh/m, v in m/s) by one step dt under the applied time gap ``h`` (s), held
    over the step, in ``p.substeps`` solver steps of dt / substeps.

    Args:
        rho: density (veh/m), shape (n_points,).
        v: speed (m/s), shape (n_points,).
        h: applied time gap (s), shape (n_points,).
        p: parameters (scheme, dx, dt, substeps, physical constants).
        alpha: plant penetration rate for this step (defaults to ``p.alpha``).
    Returns:
        (rho_new, v_new, F_in, F_out): the new state and the time-averaged mass fluxes (veh/s)
        through the inlet and the outlet during the step, so that
        dx * sum(rho_new[1:]) - dx * sum(rho[1:]) = (F_in - F_out) dt.
    Raises:
        ValueError: for an unknown ``p.scheme`` (``model.schemes.get_scheme``).
    """
    chex.assert_rank([rho, v, h], 1)
    chex.assert_equal_shape([rho, v, h])
    a = p.alpha if alpha is None else alpha
    scheme = get_scheme(p.scheme)
    if p.substeps == 1:
        return solver_step(rho, v, h, a, p, p.dt, scheme)
    dt = p.solver_dt

    def body(_, carry):
        r, u, f_in, f_out = carry
        r, u, fi, fo = solver_step(r, u, h, a, p, dt, scheme)
        return r, u, f_in + fi, f_out + fo

    zero = jnp.zeros((), rho.dtype)
    r, u, f_in, f_out = jax.lax.fori_loop(0, p.substeps, body, (rho, v, zero, zero))
    return r, u, f_in / p.substeps, f_out / p.substeps


def is_physical(rho: Array, v: Array, p: TrafficParams) -> Array:
    """True when the state is finite and in the physical region 0 < rho < 1/l, 0 <= v < inf.

    One fused reduction: a NaN fails every comparison, an infinite rho fails rho < 1/l.
    """
    return jnp.all(fundamental.in_physical_region(rho, v, p.l))


def local_cfl(rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None) -> Array:
    """CFL number max(|lambda1|, |lambda2|) dt_s/dx at every node for the current state (dt_s: the
    solver step dt / substeps)."""
    lam2, _ = _speeds_and_source(rho, v, h, p.alpha if alpha is None else alpha, p)
    return jnp.maximum(jnp.abs(v), jnp.abs(lam2)) * (p.solver_dt / p.dx)


def max_cfl(rho: Array, v: Array, h: Array, p: TrafficParams, alpha: Array | float | None = None) -> Array:
    """Largest CFL number max_i |lambda_k| dt/dx over the grid for the current state."""
    return jnp.max(local_cfl(rho, v, h, p, alpha))
