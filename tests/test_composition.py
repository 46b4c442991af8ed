"""The composed numerical core (model.reconstruction, model.time_stepping, model.boundary, model.schemes):
the scheme table reproduces the hand-written upwind/Euler and MUSCL/Heun steps bit for bit, and unknown or
malformed pieces are rejected with a clear message."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic import TrafficParams, paper_initial_condition
from jaxtraffic.model import schemes, solver
from jaxtraffic.model.reconstruction import limited_slopes
from jaxtraffic.model.time_stepping import FORWARD_EULER, SSP_RK2, ShuOsherTableau, rk_step


def _hand_rhs(rho, v, h, alpha, p, second_order):
    """The semi-discrete right-hand side as written before the split (one branch per scheme)."""
    inv_dx = 1.0 / p.dx
    q = rho * v
    face = q[1:-1] + 0.5 * limited_slopes(q)[1:-1] if second_order else q[1:-1]
    f_in, f_out = q[0], q[-1]
    flux = jnp.concatenate([f_in[None], face, f_out[None]])
    drho = jnp.concatenate([jnp.zeros((1,), rho.dtype), (flux[:-1] - flux[1:]) * inv_dx])
    lam2, source = solver._speeds_and_source(rho, v, h, alpha, p)
    if second_order:
        s = limited_slopes(v)
        right, left = v - 0.5 * s, v + 0.5 * s
        vx_fwd = (right[1:] - right[:-1]) * inv_dx
        vx_bwd = (left[1:] - left[:-1]) * inv_dx
    else:
        vx_fwd = (v[1:] - v[:-1]) * inv_dx
        vx_bwd = vx_fwd
    vx_b = jnp.concatenate([vx_fwd[:1], vx_bwd[:-1]])
    vx = jnp.where(lam2[:-1] < 0, vx_fwd, vx_b)
    adv = jnp.concatenate([lam2[:-1] * vx, jnp.zeros((1,), v.dtype)])
    return drho, source - adv, f_in, f_out


def _hand_step(rho, v, h, alpha, p, dt):
    """Forward Euler (upwind) and Heun (MUSCL) written out by hand, with the inlet rho_0 = q_in / v_0."""
    def inlet(r, u):
        return r.at[0].set(p.q_in / u[0])

    if p.scheme == "upwind":
        drho, dv, f_in, f_out = _hand_rhs(rho, v, h, alpha, p, False)
        rho1, v1 = rho + dt * drho, v + dt * dv
        return inlet(rho1, v1), v1, f_in, f_out
    drho, dv, f_in0, f_out0 = _hand_rhs(rho, v, h, alpha, p, True)
    rho1, v1 = rho + dt * drho, v + dt * dv
    rho1 = inlet(rho1, v1)
    drho1, dv1, f_in1, f_out1 = _hand_rhs(rho1, v1, h, alpha, p, True)
    rho2, v2 = 0.5 * (rho + rho1 + dt * drho1), 0.5 * (v + v1 + dt * dv1)
    return inlet(rho2, v2), v2, 0.5 * (f_in0 + f_in1), 0.5 * (f_out0 + f_out1)


@pytest.mark.parametrize("scheme", ["upwind", "muscl"])
@pytest.mark.parametrize("jit", [False, True])
def test_composed_step_is_the_hand_written_scheme_bit_for_bit(scheme, jit):
    p = TrafficParams(n_points=11, L=200.0, scheme=scheme)
    rho, _ = paper_initial_condition(p, amplitude=0.03, wavenumber=1.0)
    v = jnp.linspace(2.0, 25.0, p.n_points)  # fast at the outlet end: lambda2 changes sign along the road
    h = jnp.linspace(0.8, 2.5, p.n_points)
    alpha = jnp.float32(0.3)

    def composed(r, u):
        return solver.solver_step(r, u, h, alpha, p, p.dt)

    def hand(r, u):
        return _hand_step(r, u, h, alpha, p, p.dt)

    if jit:
        composed, hand = jax.jit(composed), jax.jit(hand)
    for _ in range(3):  # a few steps, each compared exactly
        got, want = composed(rho, v), hand(rho, v)
        for a, b in zip(got, want, strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b)), scheme
        rho, v = got[0], got[1]
    lam2, _ = solver._speeds_and_source(rho, v, h, alpha, p)
    assert np.any(np.asarray(lam2) < 0) and np.any(np.asarray(lam2) > 0)  # both upwind directions were used


def test_scheme_table_maps_the_names_to_their_pieces():
    assert schemes.get_scheme("upwind").integrator is FORWARD_EULER
    assert schemes.get_scheme("muscl").integrator is SSP_RK2
    assert schemes.get_scheme("muscl").reconstruction.name == "muscl_minmod"
    assert schemes.get_scheme("upwind").inlet.name == "inflow_density"
    assert schemes.get_scheme("upwind").outlet.name == "speed_ode"


def test_unknown_scheme_is_a_clear_error():
    with pytest.raises(ValueError, match=r"unknown scheme 'weno5': known schemes are \('upwind', 'muscl'\)"):
        schemes.get_scheme("weno5")
    with pytest.raises(ValueError, match="scheme must be one of"):
        TrafficParams(scheme="weno5")


@pytest.mark.parametrize("sources, weights", [(((0,), (2,)), (None, 0.5)), (((0,), (1, 0)), (None, 0.5)),
                                              (((0,),), (None, 0.5)), ((), ())])
def test_malformed_tableau_is_rejected(sources, weights):
    with pytest.raises(ValueError, match="stage"):
        ShuOsherTableau("bad", sources=sources, weights=weights, flux_weight=None)


def test_rk_step_integrates_a_linear_ode_to_its_order():
    """du/dt = -u over one step: Euler gives 1 - dt, Heun 1 - dt + dt^2/2 (exactly, in float64 arithmetic)."""
    def rhs(u):
        return jax.tree.map(lambda x: -x, u), (0.0, 0.0)

    dt = 0.1
    u = (np.float64(1.0),)
    euler, _ = rk_step(FORWARD_EULER, rhs, lambda x: x, u, dt)
    heun, _ = rk_step(SSP_RK2, rhs, lambda x: x, u, dt)
    assert float(euler[0]) == pytest.approx(1 - dt, abs=1e-15)
    assert float(heun[0]) == pytest.approx(1 - dt + dt * dt / 2, abs=1e-15)
