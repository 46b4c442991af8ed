"""The stability certificate of the delayed three-gain law (control.stability) against theory and simulation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

import jaxtraffic as jt
from jaxtraffic.control.gain_law import lyapunov_equivalent_gains
from jaxtraffic.control.stability import GROWTH_TOL, certify, growth_rates, stable_region, wavenumbers
from jaxtraffic.model.linear import linearize
from jaxtraffic.sim.initial import paper_initial_condition

P = jt.TrafficParams()
POINTWISE = (-0.18, -0.30, -0.80)  # gains trained on a 401-point grid that chatter on finer ones


def test_open_loop_is_neutral_at_every_wavenumber():
    """The equilibrium wave speed equals lambda2 (docs/model.md section 6): the open loop neither grows nor
    decays on the line, to float32 rounding."""
    s = np.asarray(growth_rates((0.0, 0.0, 0.0), P, 4.0))
    assert np.max(np.abs(s)) < 2e-4


def test_small_period_without_delay_is_the_continuous_closed_loop():
    """D = 0, eta1 = 0, T -> 0: sigma(k) -> max Re eig(A(k) + B K), the undelayed feedback."""
    with jax.enable_x64(True):
        p = jt.TrafficParams(dt=0.001, max_delay_steps=10)
        lm = linearize(p)
        g = (0.0, -0.5, -1.5)
        ks = np.array([2 * np.pi / 250.0, 2 * np.pi / 30.0])
        s = np.asarray(growth_rates(g, p, 0.0, jnp.asarray(ks)))
        rb, vb, hb = float(lm.rho_bar), float(lm.v_bar), float(lm.h_bar)
        for k, got in zip(ks, s, strict=True):
            A = np.array([[-1j * k * vb, -1j * k * rb],
                          [float(lm.V_rho) / float(lm.tau), -1j * k * float(lm.lam2) - 1 / float(lm.tau)]])
            BK = np.outer([0, float(lm.V_h) / float(lm.tau)], hb * np.array([g[2] / rb, -g[1] / vb]))
            assert got == pytest.approx(np.max(np.linalg.eigvals(A + BK).real), abs=2e-3)


def test_zero_order_hold_matches_the_matrix_exponential_of_the_plant():
    """Growth of the open loop with the input as a state: the discretisation is exact (e^{A T})."""
    with jax.enable_x64(True):
        lm = linearize(P)
        k = 2 * np.pi / 50.0
        A = np.array([[-1j * k * float(lm.v_bar), -1j * k * float(lm.rho_bar)],
                      [float(lm.V_rho) / float(lm.tau), -1j * k * float(lm.lam2) - 1 / float(lm.tau)]])
        expected = np.log(np.max(np.abs(np.linalg.eigvals(sl.expm(A * 0.1))))) / 0.1
        got = float(growth_rates((0.0, 0.0, 0.0), P, 0.0, jnp.asarray([k]))[0])
        assert got == pytest.approx(expected, abs=1e-9)


def test_lyapunov_law_is_certified_without_delay_and_not_with_it():
    """D = 0: stable at every wavelength the paper grid resolves, and on the PDE at every wavelength above
    0.75 m (below it a wave moves a whole wavelength within a control period: the sampling alone destabilises
    it; a 2 m filter removes that). D = 4 s: unstable at tens of metres."""
    g = np.asarray(lyapunov_equivalent_gains(1.0, P))
    assert certify(g, P, 0.0, symbol="upwind").stable and certify(g, P, 0.0, sigma=2.0).stable
    k = wavenumbers(1000.0)
    s = np.asarray(growth_rates(g, P, 0.0, jnp.asarray(k)))
    assert np.all(s[2 * np.pi / k > 0.75] <= GROWTH_TOL) and s.max() > 0.01
    c = certify(g, P, 4.0)
    assert not c.stable and c.max_growth > 0.03 and c.worst_wavelength > 10.0


def test_pointwise_gains_chatter_on_the_pde_but_not_on_the_paper_grid_and_a_filter_certifies_them():
    """The issue-25 finding in the certificate: unstable on the PDE at wavelengths of tens of metres, stable
    under the paper grid's upwind differences (numerical diffusion), and stable with a 20 m filter."""
    pde = certify(POINTWISE, P, 4.0)
    assert not pde.stable and 10.0 < pde.worst_wavelength < 60.0 and pde.max_growth > 0.03
    assert certify(POINTWISE, P, 4.0, symbol="upwind").stable  # dx = 5 m
    assert not certify(POINTWISE, P, 4.0, symbol="upwind", dx=0.625).stable  # 1601 points
    assert certify(POINTWISE, P, 4.0, sigma=20.0).stable


def test_certificate_predicts_the_simulated_growth():
    """Linearised plant on a 101-point upwind grid, D = 4 s, a small cosine perturbation: gains the
    certificate (upwind symbol) says grow at > 0.01/s grow in the simulation at about that rate; gains it
    certifies decay."""
    p = jt.TrafficParams(n_points=101, delay=4.0, model="linear")
    rho0, v0 = paper_initial_condition(p, amplitude=1e-4)
    for gains, unstable in (((0.0, -2.0, -4.0), True), ((0.0, -1.0, -1.5), False)):
        cert = certify(gains, p, 4.0, symbol="upwind")
        res = jt.simulate(p, jt.constant_gains(*gains), n_steps=3000, record=jt.Record(every=100), rho0=rho0, v0=v0)
        l2 = np.asarray(res.trajectory.rho_L2)
        rate = np.log(float(res.metrics["final_rho_L2"]) / l2[10]) / 200.0  # 100 s -> 300 s
        if unstable:
            assert cert.max_growth > 0.01 and rate > 0.5 * cert.max_growth, (cert, rate)
        else:
            assert cert.stable and cert.max_growth <= GROWTH_TOL and rate < 0.0, (cert, rate)


def test_stable_region_grid_agrees_with_certify():
    e2, e3 = np.array([-1.0, -2.0]), np.array([-1.5, -4.0])
    region = stable_region(P, 4.0, 0.0, e2, e3, sigma=20.0)
    assert region.shape == (2, 2)
    k = jnp.asarray(wavenumbers(1000.0, n=96))
    for i, j in ((0, 0), (1, 1)):
        direct = float(jnp.max(growth_rates((0.0, e2[i], e3[j]), P, 4.0, k, 20.0)))
        assert region[i, j] == pytest.approx(direct, abs=1e-6)


def test_growth_rate_gradient_matches_finite_differences():
    """The dominant eigenvalue's derivative by perturbation theory (``dominant_eigenvalue``) against central
    differences, float64, at one wavenumber of the unstable band (where the dominant eigenvalue is simple)."""
    from jaxtraffic.control.stability import model_growth_rates

    with jax.enable_x64(True):
        lm = linearize(jt.TrafficParams())
        k = jnp.asarray([2 * np.pi / 30.0])

        def f(g):
            return model_growth_rates(g, lm, 40, k, 5.0, differentiable=True)[0]

        g0 = jnp.asarray([0.1, -0.8, -1.2])
        grad = np.asarray(jax.grad(f)(g0))
        eps = 1e-5
        fd = [(float(f(g0.at[i].add(eps))) - float(f(g0.at[i].add(-eps)))) / (2 * eps) for i in range(3)]
        np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-7)
        assert np.max(np.abs(fd)) > 1e-3  # the test is not trivial
        assert float(model_growth_rates(g0, lm, 40, k, 5.0)[0]) == pytest.approx(float(f(g0)), abs=1e-10)


def test_certificate_penalty_is_zero_when_certified_and_pushes_towards_it():
    """``learn.gradient.certificate_penalty``: 0 for certified gains, positive for pointwise gains at D = 4 s,
    and a small step against its gradient lowers it."""
    from jaxtraffic.learn.gradient import objective

    base = jt.TrafficParams(delay=4.0)
    cfg = objective.GradientConfig(filter_sigma=0.0)
    pen, g = objective.penalty_and_grad(jnp.asarray(POINTWISE), cfg, base, (40,))
    assert float(pen) > 0.03
    pen2, _ = objective.penalty_and_grad(jnp.asarray(POINTWISE) - 0.5 * g / jnp.linalg.norm(g), cfg, base, (40,))
    assert float(pen2) < float(pen)
    filtered = objective.GradientConfig(filter_sigma=25.0)
    assert float(objective.penalty_and_grad(jnp.asarray(POINTWISE), filtered, base, (40,))[0]) == 0.0


def test_a_growing_mode_is_marginal_not_certified():
    """Issue 47, item 7: a positive growth rate below the training's tolerance is "marginal", never "certified"."""
    from jaxtraffic.control.stability import GROWTH_TOL, verdict

    assert verdict(-1e-4) == "certified" and verdict(0.0) == "certified"
    assert verdict(5.1e-4) == "marginal" and verdict(GROWTH_TOL) == "marginal"
    assert verdict(2 * GROWTH_TOL) == "not certified"
