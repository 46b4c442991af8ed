"""Tests of the linearised model (docs/model.md section 6) and of its discrete step."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic import TrafficParams, constant_gains, equilibrium, simulate
from jaxtraffic.control import lyapunov_equivalent_gains
from jaxtraffic.model import fundamental as fd
from jaxtraffic.model.linear import gain_law_is_regular, gain_law_wave_speed, linear_step, linearize, riemann_w
from jaxtraffic.model.solver import arz_step
from jaxtraffic.sim import Record


def test_coefficients_match_model_table():
    """Oracles of the docs/model.md section 2.4 table, in float64."""
    with jax.enable_x64(True):
        lm = linearize(TrafficParams())
        np.testing.assert_allclose(float(lm.tau), 11.214953, rtol=1e-6)
        np.testing.assert_allclose(float(lm.V_rho), -62.43492, rtol=1e-6)
        np.testing.assert_allclose(float(lm.V_h), -1.612903, rtol=1e-6)
        np.testing.assert_allclose(float(lm.lam1), 3.10484, rtol=1e-5)
        np.testing.assert_allclose(float(lm.lam2), -3.59813, rtol=1e-5)
        # lambda2 = v_bar + rho_bar V_rho = -l / h_mix(h_bar)
        np.testing.assert_allclose(float(lm.lam2), float(lm.v_bar + lm.rho_bar * lm.V_rho), rtol=1e-12)
        np.testing.assert_allclose(float(lm.lam2), -5.0 / 1.389610, rtol=1e-6)


def test_inlet_condition_in_riemann_variables():
    """rho~(0) = -(rho_bar/v_bar) v~(0) is w(0) = (lambda2/lambda1) v~(0)."""
    with jax.enable_x64(True):
        lm = linearize(TrafficParams())
        v0 = jnp.asarray(0.37)
        w0 = riemann_w(-(lm.rho_bar / lm.v_bar) * v0, v0, lm)
        np.testing.assert_allclose(float(w0), float(lm.lam2 / lm.lam1 * v0), rtol=1e-12)


@pytest.mark.parametrize("alpha,q_in", [(0.15, 1.0 / 3.0), (0.4, 0.3)])
def test_linear_step_is_jacobian_of_upwind_step(alpha, q_in):
    """Central finite difference of the nonlinear upwind step at the equilibrium, float64.

    With eps = 1e-6 relative perturbations the truncation error is O(eps^2) ~ 1e-12 and the
    rounding error O(1e-16/eps) ~ 1e-10, so a relative tolerance of 1e-7 is loose for a correct
    Jacobian and tight for any wrong coefficient (which would be off by O(1)).
    """
    with jax.enable_x64(True):
        p = TrafficParams(n_points=21, alpha=alpha, q_in=q_in)
        lm = linearize(p)
        rho_bar, v_bar = equilibrium(p)
        n = p.n_points
        k1, k2, k3 = jax.random.split(jax.random.PRNGKey(3), 3)
        d_rho = rho_bar * jax.random.normal(k1, (n,), jnp.float64)
        d_v = v_bar * jax.random.normal(k2, (n,), jnp.float64)
        d_h = p.h_bar * jax.random.normal(k3, (n,), jnp.float64)
        rho = jnp.full((n,), rho_bar)
        v = jnp.full((n,), v_bar)
        h = jnp.full((n,), p.h_bar)
        eps = 1e-6

        def step(s):
            r, vv, _, _ = arz_step(rho + s * d_rho, v + s * d_v, h + s * d_h, p)
            return r, vv

        (rp, vp), (rm, vm) = step(eps), step(-eps)
        fd_rho, fd_v = (rp - rm) / (2 * eps), (vp - vm) / (2 * eps)
        lin_rho, lin_v = linear_step(d_rho, d_v, d_h, lm)
        np.testing.assert_allclose(np.asarray(lin_rho), np.asarray(fd_rho), rtol=1e-7,
                                   atol=1e-7 * float(jnp.max(jnp.abs(fd_rho))))
        np.testing.assert_allclose(np.asarray(lin_v), np.asarray(fd_v), rtol=1e-7,
                                   atol=1e-7 * float(jnp.max(jnp.abs(fd_v))))
        # and the forward-mode derivative agrees too (exact Jacobian-vector product)
        _, (jr, jv) = jax.jvp(lambda s: step(s), (0.0,), (1.0,))
        np.testing.assert_allclose(np.asarray(lin_rho), np.asarray(jr), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(lin_v), np.asarray(jv), rtol=1e-10, atol=1e-12)


def test_linear_step_fixed_point_and_input_channel():
    """Zero deviation stays zero; a uniform input moves only v~, by dt V_h U / tau_mix."""
    with jax.enable_x64(True):
        p = TrafficParams(n_points=21)
        lm = linearize(p)
        z = jnp.zeros(p.n_points)
        r, v = linear_step(z, z, z, lm)
        assert float(jnp.max(jnp.abs(r))) == 0.0 and float(jnp.max(jnp.abs(v))) == 0.0
        U = jnp.full(p.n_points, 0.2)
        r, v = linear_step(z, z, U, lm)
        expected_v = float(p.dt * lm.V_h * 0.2 / fd.tau_mix(p))
        np.testing.assert_allclose(np.asarray(v), expected_v, rtol=1e-12)
        # the inlet density follows the boundary condition; the interior density is untouched
        np.testing.assert_allclose(float(r[0]), float(-(lm.rho_bar / lm.v_bar) * expected_v), rtol=1e-12)
        assert float(jnp.max(jnp.abs(r[1:]))) == 0.0


def test_gain_law_wave_speed_oracles():
    """Open loop: the second characteristic speed lambda2 = v_bar + rho_bar V_rho (< 0, congested).
    The Lyapunov-equivalent gains make v~ = 0 in the relaxed state: density is carried at v_bar."""
    with jax.enable_x64(True):
        p = TrafficParams()
        lm = linearize(p)
        np.testing.assert_allclose(float(gain_law_wave_speed(jnp.zeros(3), lm)), float(lm.lam2), rtol=1e-12)
        for k in (0.5, 1.0, 2.0):
            g = lyapunov_equivalent_gains(k, p)
            np.testing.assert_allclose(float(gain_law_wave_speed(g, lm)), float(lm.v_bar), rtol=1e-12)
        # batched over leading axes
        assert gain_law_wave_speed(jnp.zeros((4, 2, 3)), lm).shape == (4, 2)
        # the relaxed relation breaks down where 1 + V_h h_bar eta2 / ((1 + eta1) v_bar) = 0
        e2_sing = -float(lm.v_bar / (lm.V_h * lm.h_bar))  # 1.283333 at eta1 = 0
        assert bool(gain_law_is_regular(jnp.array([0.0, 0.9 * e2_sing, 0.0]), lm))
        assert not bool(gain_law_is_regular(jnp.array([0.0, 1.1 * e2_sing, 0.0]), lm))


# (eta1, eta2, eta3): s = v_bar (Lyapunov k = 1), s ~ +1.5 m/s, s ~ -1.5 m/s, open loop (s = lambda2)
WAVE_GAINS = [(0.0, 0.0, -2.7705607), (-0.49, -0.81, -0.64), (0.028, -0.183, -0.628), (0.0, 0.0, 0.0)]


def test_wave_speed_decides_whether_a_density_offset_leaves_the_road():
    """Constant gains on a 200 m road (41 points, D = 1 s) from a uniform +2 veh/km offset: with s > 0
    the offset is carried out at the outlet within about L / s (plus the relaxation time), with
    s < 0 it stays and grows from the inlet."""
    p = TrafficParams(n_points=41, L=200.0, delay=1.0)
    lm = linearize(p)
    rho_bar, _ = equilibrium(p)
    rho0 = jnp.full((p.n_points,), rho_bar + 0.002)
    for gains in WAVE_GAINS:
        s = float(gain_law_wave_speed(jnp.asarray(gains), lm))
        res = simulate(p, constant_gains(*gains), rho0=rho0, v0=p.q_in / rho0, n_steps=2000, record=Record(every=100))
        l2 = np.asarray(res.trajectory.rho_L2)  # every 10 s, 10 .. 200 s
        if s > 0:
            flushed = int(np.ceil((p.L / s + 2 * float(lm.tau)) / 10.0)) - 1  # index of t >= L/s + 2 tau
            assert np.all(np.diff(l2[:flushed + 1]) < 0), (gains, s, l2)
            assert l2[flushed] < 0.25 * 2.0, (gains, s, l2)  # veh/km: a quarter of the 2 veh/km offset
        else:
            grow = l2[:15]  # 10 .. 150 s (the open loop leaves the physical region later)
            assert np.all(np.diff(grow) > 0) and grow[-1] > 2 * 2.0, (gains, s, l2)
