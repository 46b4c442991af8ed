"""Tests of the linearised model (MODEL.md section 6) and of its discrete step."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic import TrafficParams, equilibrium
from jaxtraffic import fundamental as fd
from jaxtraffic.linear import linear_step, linearize, riemann_w
from jaxtraffic.solver import arz_step


def test_coefficients_match_model_table():
    """Oracles of the MODEL.md section 2 table, in float64."""
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
