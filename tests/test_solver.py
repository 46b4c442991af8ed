"""ARZ solver (docs/model.md section 3): fixed point, exact mass balance, CFL, convergence order."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL, bump_state, run_solver

from jaxtraffic import TrafficParams, equilibrium, equilibrium_state
from jaxtraffic.model.solver import arz_step, is_physical, max_cfl, minmod

SCHEMES = ("upwind", "muscl")


# ----------------------------------------------------------------------------- fixed point
@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("kw", [{}, {"alpha": 0.6, "q_in": 0.3}])
def test_equilibrium_is_a_fixed_point_float64(x64, scheme, kw):
    p = TrafficParams(scheme=scheme, **SMALL, **kw)
    rho_bar, v_bar = equilibrium(p)
    rho, v = equilibrium_state(p, jnp.float64)
    r, u, _, _ = run_solver(rho, v, p, 4000)
    np.testing.assert_allclose(r, rho_bar, rtol=1e-12, atol=0)
    np.testing.assert_allclose(u, v_bar, rtol=1e-12, atol=0)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_equilibrium_is_a_fixed_point_float32(scheme):
    p = TrafficParams(scheme=scheme, **SMALL)
    rho_bar, v_bar = equilibrium(p)
    rho, v = equilibrium_state(p)
    r, u, _, _ = run_solver(rho, v, p, 4000)
    np.testing.assert_allclose(r, rho_bar, rtol=1e-5, atol=0)
    np.testing.assert_allclose(u, v_bar, rtol=1e-5, atol=0)


def test_a_perturbation_does_move_the_state():
    """Guard for the fixed-point tests: the solver is not the identity."""
    p = TrafficParams(**SMALL)
    rho, v = bump_state(p)
    r, u, _, _ = run_solver(rho, v, p, 50)
    assert float(jnp.max(jnp.abs(r - rho))) > 1e-4 and float(jnp.max(jnp.abs(u - v))) > 1e-2


# ----------------------------------------------------------------------------- mass balance
@pytest.mark.parametrize("scheme", SCHEMES)
def test_exact_discrete_mass_balance(x64, scheme):
    """dx * sum(rho[1:]) changes by exactly (F_in - F_out) dt every step, to rounding."""
    p = TrafficParams(scheme=scheme, **SMALL)
    # a density and speed bump that reaches the outlet, plus a speed ripple everywhere
    rho, v = bump_state(p, amp_rho=0.01, amp_v=0.3, centre=0.8, width=0.1, dtype=jnp.float64)
    v = v * (1.0 + 0.01 * jnp.sin(jnp.linspace(0.0, 11.0, p.n_points)))
    rho = rho.at[0].set(p.q_in / v[0])
    n = 400
    _, _, mass, (f_in, f_out) = run_solver(rho, v, p, n)
    mass, f_in, f_out = np.asarray(mass), np.asarray(f_in), np.asarray(f_out)
    dm = np.diff(mass)
    budget = (f_in - f_out) * float(p.dt)
    scale = mass[0]
    assert np.max(np.abs(dm - budget)) < 1e-13 * scale
    # accumulated over all steps (no drift)
    assert abs((mass[-1] - mass[0]) - budget.sum()) < 1e-12 * scale
    # the test is not trivial: the mass and the outflow really change
    assert abs(mass[-1] - mass[0]) > 1e-3 * scale
    assert np.ptp(f_out) > 1e-3 * float(p.q_in)
    # inflow is the boundary condition q_in (rho_0 = q_in / v_0)
    np.testing.assert_allclose(f_in, float(p.q_in), rtol=1e-13)


def test_fluxes_of_the_upwind_step(x64):
    p = TrafficParams(**SMALL)
    rho, v = bump_state(p, centre=0.95, dtype=jnp.float64)
    r1, v1, f_in, f_out = arz_step(rho, v, jnp.full_like(rho, p.h_bar), p)
    np.testing.assert_allclose(f_out, rho[-1] * v[-1], rtol=1e-15)
    np.testing.assert_allclose(f_in, rho[0] * v[0], rtol=1e-15)
    np.testing.assert_allclose(r1[0] * v1[0], p.q_in, rtol=1e-14)  # inlet BC after the step


def test_float32_mass_balance_to_rounding():
    p = TrafficParams(**SMALL)
    rho, v = bump_state(p, centre=0.8)
    _, _, mass, (f_in, f_out) = run_solver(rho, v, p, 200)
    assert np.all(np.isfinite(np.asarray(mass)))
    dm = np.diff(np.asarray(mass, np.float64))
    budget = (np.asarray(f_in, np.float64) - np.asarray(f_out, np.float64)) * float(p.dt)
    assert np.max(np.abs(dm - budget)) < 1e-5 * float(mass[0])


# ----------------------------------------------------------------------------- boundary / misc
def test_alpha_argument_overrides_params(x64):
    p = TrafficParams(**SMALL)
    rho, v = bump_state(p, dtype=jnp.float64)
    h = jnp.full_like(rho, 1.2)
    a = arz_step(rho, v, h, p, 0.4)
    b = arz_step(rho, v, h, p.replace(alpha=0.4))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-14)
    c = arz_step(rho, v, h, p)
    assert not np.allclose(a[1], c[1], rtol=1e-10)


def test_is_physical():
    p = TrafficParams(**SMALL)
    rho, v = equilibrium_state(p)
    assert bool(is_physical(rho, v, p))
    assert not bool(is_physical(rho.at[3].set(-1e-3), v, p))
    assert not bool(is_physical(rho.at[3].set(0.0), v, p))
    assert not bool(is_physical(rho.at[3].set(1.0 / p.l), v, p))  # jam density excluded
    assert not bool(is_physical(rho, v.at[5].set(-1e-3), p))
    assert bool(is_physical(rho, v.at[5].set(0.0), p))
    assert not bool(is_physical(rho.at[2].set(jnp.nan), v, p))
    assert not bool(is_physical(rho, v.at[2].set(jnp.inf), p))
    assert not bool(is_physical(rho, v.at[2].set(jnp.nan), p))


def test_max_cfl_at_equilibrium_matches_construction_check():
    from jaxtraffic import cfl_number

    p = TrafficParams()
    rho, v = equilibrium_state(p)
    assert float(max_cfl(rho, v, jnp.full_like(rho, p.h_bar), p)) == pytest.approx(cfl_number(p), rel=1e-5)


def test_minmod():
    a = jnp.array([1.0, -2.0, 3.0, 0.0, -1.0])
    b = jnp.array([2.0, -1.0, -3.0, 5.0, -4.0])
    np.testing.assert_array_equal(minmod(a, b), [1.0, -1.0, 0.0, 0.0, -1.0])


# ----------------------------------------------------------------------------- convergence order
T_CONV = 20.0  # s: the bump (centre L/2, width 50 m) stays far from both boundaries


def _bump_solution(n_cells: int, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """Solution at T_CONV on nodes x_i = i L / n_cells (nested grids), CFL ~ 0.18."""
    dx = 1000.0 / n_cells
    p = TrafficParams(n_points=n_cells + 1, dt=dx / 20.0, scheme=scheme)
    rho, v = bump_state(p, amp_rho=0.01, amp_v=0.3, centre=0.5, width=0.05, dtype=jnp.float64)
    r, u, _, _ = run_solver(rho, v, p, int(round(T_CONV / float(p.dt))))
    return np.asarray(r), np.asarray(u)


def _orders(scheme: str, grids=(100, 200, 400), ref_cells: int = 3200):
    # reference: the second-order scheme on a much finer nested grid
    ref_r, ref_v = _bump_solution(ref_cells, "muscl")
    errs = []
    for n in grids:
        r, u = _bump_solution(n, scheme)
        s = ref_cells // n
        errs.append((np.mean(np.abs(r - ref_r[::s])), np.mean(np.abs(u - ref_v[::s]))))
    errs = np.asarray(errs)
    return np.log2(errs[:-1] / errs[1:]), errs


@pytest.fixture(scope="module")
def orders():
    with jax.enable_x64(True):
        return {s: _orders(s) for s in SCHEMES}


def test_upwind_is_first_order(orders):
    o, errs = orders["upwind"]
    assert np.all(errs[1:] < errs[:-1])
    assert np.all((o > 0.75) & (o < 1.3)), o


def test_muscl_is_second_order(orders):
    o, errs = orders["muscl"]
    assert np.all(o > 1.5), o
    # and more accurate than upwind on the same grid
    assert np.all(errs < orders["upwind"][1])


@pytest.mark.parametrize("scheme", SCHEMES)
def test_substeps_are_solver_steps_of_dt_over_substeps(x64, scheme):
    """One step of dt with 3 substeps = three steps of dt/3 (to rounding), fluxes averaged over them, so
    the mass balance dx * sum(rho[1:]) += (F_in - F_out) dt holds for the whole step."""
    p3 = TrafficParams(scheme=scheme, substeps=3, **{**SMALL, "dt": 3 * SMALL["dt"]})
    p1 = TrafficParams(scheme=scheme, **SMALL)
    rho, v = bump_state(p1, dtype=jnp.float64)
    r3, v3, fi3, fo3 = arz_step(rho, v, jnp.full_like(rho, p1.h_bar), p3)
    r1, v1, fis, fos = rho, v, [], []
    for _ in range(3):
        r1, v1, fi, fo = arz_step(r1, v1, jnp.full_like(rho, p1.h_bar), p1)
        fis.append(fi)
        fos.append(fo)
    np.testing.assert_allclose(r3, r1, rtol=1e-13)
    np.testing.assert_allclose(v3, v1, rtol=1e-13)
    dx = float(p1.dx)
    dm = dx * (float(jnp.sum(r3[1:])) - float(jnp.sum(rho[1:])))
    assert dm == pytest.approx((float(fi3) - float(fo3)) * float(p3.dt), abs=1e-13 * dx * float(jnp.sum(rho)))
    assert float(fo3) == pytest.approx(np.mean(fos), rel=1e-13)
