"""The learned residual on adaptive backstepping (``control.adaptive_residual``; ``--policy residual``), tiny grids."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_told_delay_run

from jaxtraffic import TrafficParams, simulate, simulate_batch, stack_params
from jaxtraffic.cli.train import config_from_args
from jaxtraffic.control import adaptive_backstepping, takes_delay, tell_delay
from jaxtraffic.control.adaptive_residual import adaptive_residual, interp2, residual_gains
from jaxtraffic.learn.gradient import objective
from jaxtraffic.sim import paper_initial_condition

N, STEPS = 41, 200
NOMINAL = TrafficParams(n_points=N, delay=2.0)
TABLE = jnp.asarray(np.random.default_rng(0).normal(0.0, 0.3, (3, 3, 2)), jnp.float32)


def _run(ctrl, plant=NOMINAL, n_steps=STEPS):
    rho0, v0 = paper_initial_condition(NOMINAL)
    return simulate(plant, ctrl, n_steps=n_steps, rho0=rho0, v0=v0, nominal=NOMINAL)


@pytest.mark.parametrize("alpha", [0.15, 0.45])
def test_zero_residual_is_the_adaptive_law(alpha):
    """Its correction is exactly 0; the closed loops agree to float rounding (XLA fuses the two programs
    differently: measured 1 ulp of density after 200 steps)."""
    plant = NOMINAL.replace(alpha=alpha)
    a = _run(adaptive_backstepping(delay=2.0), plant)
    r = _run(adaptive_residual(delay=2.0), plant)
    np.testing.assert_allclose(np.asarray(r.final.rho), np.asarray(a.final.rho), rtol=1e-6, atol=0)
    np.testing.assert_allclose(np.asarray(r.final.v), np.asarray(a.final.v), rtol=1e-6, atol=0)
    np.testing.assert_allclose(float(r.controller_state.alpha_hat), float(a.controller_state.alpha_hat), rtol=1e-6)
    obs = a.final.observation(plant)  # one step from the same state and estimator state: the same h, bit for bit
    if True:
        ad, res = adaptive_backstepping(delay=2.0), adaptive_residual(delay=2.0)
        cs = ad.init(obs, NOMINAL)
        h_a, _ = ad.act(cs, obs, NOMINAL, jax.random.PRNGKey(0))
        h_r, _ = res.act(cs, obs, NOMINAL, jax.random.PRNGKey(0))
        np.testing.assert_array_equal(np.asarray(h_r), np.asarray(h_a))


def test_bilinear_table_interpolates_and_holds():
    dk, ak = jnp.asarray([0.0, 4.0, 8.0]), jnp.asarray([0.05, 0.3, 0.6])
    np.testing.assert_allclose(interp2(4.0, 0.3, dk, ak, TABLE), TABLE[1, 1], rtol=1e-6)
    np.testing.assert_allclose(interp2(2.0, 0.3, dk, ak, TABLE), (TABLE[0, 1] + TABLE[1, 1]) / 2, rtol=1e-5)
    np.testing.assert_allclose(interp2(12.0, 0.9, dk, ak, TABLE), TABLE[2, 2], rtol=1e-6)  # held beyond the knots
    ctrl = adaptive_residual(TABLE, 6.0)
    np.testing.assert_allclose(residual_gains(ctrl.settings, jnp.asarray(0.05)), (TABLE[1, 0] + TABLE[2, 0]) / 2,
                               rtol=1e-5)


def test_a_correction_changes_the_law_and_tell_delay_batches():
    ctrl = adaptive_residual(jnp.broadcast_to(jnp.asarray([0.0, 0.4]), (3, 3, 2)), 2.0)
    assert takes_delay(ctrl)
    base = _run(adaptive_residual(delay=2.0))
    res = _run(ctrl)
    assert not bool(res.final.diverged)
    assert not np.array_equal(np.asarray(base.final.rho), np.asarray(res.final.rho))
    batch = tell_delay(ctrl, jnp.asarray([1.0, 3.0]))
    plants = stack_params(*(NOMINAL.replace(delay=d, alpha=a) for d, a in ((1.0, 0.15), (3.0, 0.4))))
    out = jax.jit(lambda c: simulate_batch(plants, c, n_steps=50, nominal=NOMINAL, batch_controller=True))(batch)
    assert not np.any(np.asarray(out.metrics["diverged"]))
    assert abs(float(out.controller_state.alpha_hat[1]) - 0.4) < 0.02  # the estimator state is the adaptive law's


def test_bad_tables_are_refused():
    with pytest.raises(ValueError, match="shape"):
        adaptive_residual(jnp.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="increasing"):
        adaptive_residual(alpha_knots=(0.3, 0.1, 0.6))


def test_gradient_of_the_table_is_finite():
    """Forward mode (the predictor's loop over the told delay has dynamic bounds: no reverse mode, so the
    residual trains by CEM, and Adam is refused)."""
    rho0, v0 = paper_initial_condition(NOMINAL)

    def loss(table):
        res = simulate(NOMINAL, adaptive_residual(table, 2.0), n_steps=40, rho0=rho0, v0=v0, nominal=NOMINAL)
        return jnp.sum((res.final.rho - jnp.mean(res.final.rho)) ** 2)

    _, g = jax.jvp(loss, (jnp.zeros((3, 3, 2)),), (jnp.ones((3, 3, 2)),))
    assert np.isfinite(float(g)) and float(g) != 0.0
    with pytest.raises(ValueError, match="cem"):
        objective.GradientConfig(policy="residual", grad_method="adam")


def test_a_residual_run_trains_by_cem_saves_and_loads(tmp_path):
    from jaxtraffic.runs.gradient.trainer import train_gradient

    out = tmp_path / "r"
    config = config_from_args(["gradient", "--policy", "residual", "--out-dir", str(out), "--quiet",
                               "--n-points", "21", "--train-delays", "2,6", "--train-alphas", "0.15,0.4",
                               "--train-horizon-s", "10", "--grad-steps", "5", "--eval-horizon-s", "10"])
    assert config.grad.grad_method == "cem" and config.grad.schedule_knots == (0.0, 4.0, 8.0)
    init = objective.init_theta(config.grad, config.plant, jax.random.PRNGKey(0))
    assert init.shape == (3, 3, 2) and not np.any(np.asarray(init))  # starts at the adaptive law
    train_gradient(config)
    check_told_delay_run(out, "residual")
    assert '"applies": false' in (out / "summary.json").read_text()  # no certificate for this law


def test_cem_holds_the_rows_below_the_alpha_floor_at_the_adaptive_law():
    """``residual_alpha_floor``: the table's rows at alpha_hat knots below it start and stay zero under CEM
    (there the residual is the adaptive law); the other rows are searched."""
    from jaxtraffic.learn.gradient import cem

    cfg = objective.GradientConfig(policy="residual", grad_method="cem", train_delays=(1.0, 5.0),
                                   train_alphas=(0.15, 0.4), train_horizon_s=10.0, record_every=10,
                                   steps_per_chunk=2, cem_population=4, schedule_knots=(0.0, 4.0, 8.0),
                                   residual_alpha_floor=0.1, init_gains=(0.0, 0.1, 0.2))
    plant = TrafficParams(n_points=21, delay=2.0)
    init = objective.init_theta(cfg, plant, jax.random.PRNGKey(0))
    assert not np.any(np.asarray(init[:, 0]))
    np.testing.assert_allclose(np.asarray(init[:, 1:]), np.broadcast_to([0.1, 0.2], (3, 2, 2)), rtol=1e-6)
    start, chunk = cem.make_train(cfg, plant)
    state, _ = chunk(start(jax.random.PRNGKey(1)))
    assert not np.any(np.asarray(state.theta[:, 0])) and not np.any(np.asarray(state.mean[:, 0]))
    assert np.any(np.asarray(state.mean[:, 1:]) != np.asarray(init[:, 1:]))  # the others moved
    everywhere = objective.trainable(dataclasses.replace(cfg, residual_alpha_floor=0.0), init)
    assert np.all(np.asarray(everywhere) == 1.0)  # the default: the whole table is trained
