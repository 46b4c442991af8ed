"""Linearisation of the ARZ model about its equilibrium (docs/model.md section 6).

With tildes for deviations, U = h - h_bar, V_rho = dV/drho and V_h = dV/dh at equilibrium:

    rho~_t + v_bar rho~_x + rho_bar v~_x = 0
    v~_t  + lambda2 v~_x = (V_rho rho~ + V_h U - v~) / tau_mix
    rho~(0) = -(rho_bar / v_bar) v~(0),   v~_t(L) = (V_rho rho~(L) + V_h U(L) - v~(L)) / tau_mix

equivalently, with the Riemann variable w = v~ - V_rho rho~,
w_t + lambda1 w_x = (-w + V_h U)/tau_mix and v~_t + lambda2 v~_x = (-w + V_h U)/tau_mix.
``linear_step`` discretises it with the first-order upwind scheme of ``solver`` (the exact
Jacobian of the nonlinear upwind step at the equilibrium, for lambda1 > 0 > lambda2).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.model import fundamental
from jaxtraffic.model.params import TrafficParams, equilibrium

Array = jax.Array


@struct.dataclass
class LinearModel:
    """Equilibrium coefficients (all traced scalars).

    rho_bar veh/m, v_bar m/s, h_bar s, V_rho m^2/(s veh), V_h m/s^2, tau s, lam1/lam2 m/s,
    dx m, dt s.
    """

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> LinearModel: ...

    rho_bar: Array
    v_bar: Array
    h_bar: Array
    V_rho: Array
    V_h: Array
    tau: Array
    lam1: Array
    lam2: Array
    dx: Array
    dt: Array


def linearize(p: TrafficParams) -> LinearModel:
    """Coefficients of the linearised model at the equilibrium of ``p`` (nominal alpha)."""
    rho_bar, v_bar = equilibrium(p)
    V_rho = fundamental.dV_drho(rho_bar, p.h_bar, p)
    lam1, lam2 = fundamental.characteristic_speeds(rho_bar, v_bar, p.h_bar, p)
    as_arr = jnp.asarray
    return LinearModel(
        rho_bar=rho_bar, v_bar=v_bar, h_bar=as_arr(p.h_bar), V_rho=as_arr(V_rho),
        V_h=as_arr(fundamental.dV_dh(rho_bar, p.h_bar, p)), tau=as_arr(fundamental.tau_mix(p)), lam1=as_arr(lam1),
        lam2=as_arr(lam2), dx=as_arr(p.dx), dt=as_arr(p.dt),
    )


def riemann_w(rho_t: Array, v_t: Array, lm: LinearModel) -> Array:
    """Riemann variable w = v~ - V_rho rho~ (m/s)."""
    return v_t - lm.V_rho * rho_t


def linear_step(rho_t: Array, v_t: Array, U: Array, lm: LinearModel) -> tuple[Array, Array]:
    """One upwind step of the linearised model for deviations (veh/m, m/s) under U = h - h_bar (s).

    Density is built by one concatenate (boundary node, interior update) rather than two scatters into a copy
    of ``rho_t``: the same arithmetic (equal results to rounding: XLA may fuse it otherwise), and in the
    predictor's loop (``control.baselines.predict``: up to D/dt of these per control step) one copy of the
    carry fewer per iteration, 1.2-1.3x faster there."""
    chex.assert_equal_shape([rho_t, v_t, U])
    dx, dt = lm.dx, lm.dt
    q = lm.v_bar * rho_t + lm.rho_bar * v_t  # linearised mass flux
    source = (lm.V_rho * rho_t + lm.V_h * U - v_t) / lm.tau
    vx_fwd = (v_t[1:] - v_t[:-1]) / dx
    vx_bwd = jnp.concatenate([vx_fwd[:1], vx_fwd[:-1]])
    vx = jnp.where(lm.lam2 < 0, vx_fwd, vx_bwd)
    adv = jnp.concatenate([lm.lam2 * vx, jnp.zeros((1,), v_t.dtype)])
    v_new = v_t + dt * (source - adv)
    inlet = -(lm.rho_bar / lm.v_bar) * v_new[:1]  # the fixed inflow: q~ = 0 at x = 0
    rho_new = jnp.concatenate([inlet, rho_t[1:] + (-dt / dx * (q[1:] - q[:-1]))])
    return rho_new, v_new


def gain_law_wave_speed(gains: Array, lm: LinearModel) -> Array:
    """Kinematic wave speed s (m/s) of the plant closed by the three-gain law with constant gains.

    ``gains = [eta1, eta2, eta3]`` (dimensionless, ``control.gain_law``), shape (..., 3).
    In a slowly varying, relaxed state (v = V(rho, h), h = h_prev) the law gives
    h~ (1 + eta1) = h_bar (-eta2 v~/v_bar + eta3 rho~/rho_bar), so v~ = c rho~ with

        c = (V_rho + V_h h_bar eta3 / ((1 + eta1) rho_bar)) / (1 + V_h h_bar eta2 / ((1 + eta1) v_bar))

    and density perturbations travel like in a first-order model, at s = v_bar + rho_bar c (the
    delay does not enter). With s > 0 they are carried out of the road at the outlet (the fixed
    inflow admits none), at s <= 0 they enter from the outlet and stay: the closed loop cannot be
    asymptotically stable. Open loop: s = lambda2 < 0 (congested, backward waves). The time to
    flush the road, L / s, bounds how fast a uniform density offset can decay.
    """
    num, den = _relaxed_slope_terms(gains, lm)
    return lm.v_bar + lm.rho_bar * num / den


def gain_law_is_regular(gains: Array, lm: LinearModel) -> Array:
    """Whether the relaxed relation v~ = c rho~ of ``gain_law_wave_speed`` holds with a finite c of
    the continuous branch (its denominator > 0); across the surface where it vanishes, s changes
    sign through infinity and means nothing. Shape gains.shape[:-1], bool."""
    return _relaxed_slope_terms(gains, lm)[1] > 0


def _relaxed_slope_terms(gains: Array, lm: LinearModel) -> tuple[Array, Array]:
    """Numerator (m^2/(s veh)) and denominator (dimensionless) of c in ``gain_law_wave_speed``."""
    e1, e2, e3 = gains[..., 0], gains[..., 1], gains[..., 2]
    scale = lm.V_h * lm.h_bar / (1.0 + e1)
    return lm.V_rho + scale * e3 / lm.rho_bar, 1.0 + scale * e2 / lm.v_bar
