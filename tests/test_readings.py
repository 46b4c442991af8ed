"""Readings of the indices and of the alpha noise: the paper's km/h units, the comfort
split and its switch-on step, and the noise readings (held, per node, seen by the model)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL

import jaxtraffic
from jaxtraffic.control.base import Controller
from jaxtraffic.sim import metrics as sim_metrics
from jaxtraffic.sim.plant import (
    NoiseReading,
    closed_loop_step,
    initial_state,
    noise_alpha_sequence,
    plant_alpha_sequence,
)


def test_fuel_rate_kmh_is_the_si_rate_of_kmh_values():
    v, a = jnp.array([3.0, 10.0, 25.0]), jnp.array([0.5, -0.2, 0.0])
    np.testing.assert_allclose(sim_metrics.fuel_rate_kmh(v, a), sim_metrics.fuel_rate(3.6 * v, 3.6 * a), rtol=1e-7)
    v_kmh = 3.6 * 10.0
    hand = 25e-3 + 24.5e-6 * v_kmh + 32.5e-9 * v_kmh**3 + 125e-6 * v_kmh * (3.6 * -0.2)
    np.testing.assert_allclose(sim_metrics.fuel_rate_kmh(v, a)[1], hand, rtol=1e-6)


@pytest.fixture(scope="module")
def delayed_run():
    p = jaxtraffic.TrafficParams(**SMALL, delay=2.0, max_delay_steps=8)
    return p, jaxtraffic.simulate(p, jaxtraffic.backstepping(2.0, 1.0), n_steps=60)


def test_index_units(delayed_run):
    _, res = delayed_run
    m = {k: float(v) for k, v in res.metrics.items()}
    assert m["J_TTT_kmh"] == m["J_TTT"]  # rho is in veh/km in both readings
    np.testing.assert_allclose(m["J_comfort_kmh"], 3.6**2 * m["J_comfort"], rtol=1e-5)
    np.testing.assert_allclose(m["J_comfort_a2_kmh"], 3.6**2 * m["J_comfort_a2"], rtol=1e-6)
    assert m["J_fuel_kmh"] > m["J_fuel"] > 0  # every b_i term grows with the speed unit


def test_comfort_parts_sum_to_the_total(delayed_run):
    _, res = delayed_run
    m = {k: float(v) for k, v in res.metrics.items()}
    np.testing.assert_allclose(m["J_comfort_a2"] + m["J_comfort_at2"], m["J_comfort"], rtol=1e-5)
    assert 0 < m["J_comfort_switch_on"] <= m["J_comfort_at2"]
    np.testing.assert_allclose(m["J_comfort_no_switch_on"], m["J_comfort"] - m["J_comfort_switch_on"],
                               rtol=1e-5)


def test_switch_on_is_the_jerk_of_step_d():
    """By hand: the a_t^2 part of step ``switch_step`` (and nothing else) goes into J_comfort_switch;
    at switch_step = 0 it is zero (a^{-1} := a^0)."""
    n, dx, dt = 5, 10.0, 0.5
    vs = [jnp.full((n,), 3.0), jnp.full((n,), 3.0), jnp.full((n,), 3.5), jnp.full((n,), 3.5)]
    rho = jnp.full((n,), 0.1)
    for switch in (0, 1):
        acc = sim_metrics.init_metrics(n)
        for k in range(3):
            record = sim_metrics.StepRecord(step=jnp.asarray(k), rho=rho, v=vs[k], v_next=vs[k + 1], h_sent=rho,
                                            cfl=0.0, active=jnp.asarray(True))
            target = sim_metrics.MetricsTarget(rho_bar=0.1, v_bar=3.0, h_bar=0.1, dx=dx, dt=dt, switch_step=switch)
            acc = sim_metrics.update_metrics(acc, record, target)
        tot = sim_metrics.totals(acc, dx)
        # a = 0, 1, 0 m/s^2 -> a_t = 0, 2, -2 m/s^3; weight dt * 1000 rho = 50 per node, L = 40 m
        expected = 0.0 if switch == 0 else 4.0 * 50.0 * 40.0
        np.testing.assert_allclose(float(tot["J_comfort_switch_on"]), expected, rtol=1e-6)
        np.testing.assert_allclose(float(tot["J_comfort_at2"]), 8.0 * 50.0 * 40.0, rtol=1e-6)
        np.testing.assert_allclose(float(tot["J_comfort_a2"]), 1.0 * 50.0 * 40.0, rtol=1e-6)


def test_switch_on_is_zero_without_delay():
    p = jaxtraffic.TrafficParams(**SMALL)
    res = jaxtraffic.simulate(p, jaxtraffic.lyapunov(1.0), n_steps=20)
    assert float(res.metrics["J_comfort_switch_on"]) == 0.0


def test_default_reading_draws_the_default_sequence():
    p = jaxtraffic.TrafficParams(**SMALL, alpha_noise=0.15)
    key = jax.random.PRNGKey(2)
    ref = plant_alpha_sequence(p, key, 40)
    for reading in (None, NoiseReading(), NoiseReading(model_sees=True)):
        np.testing.assert_array_equal(noise_alpha_sequence(p, key, 40, reading), ref)


def test_held_noise_is_constant_over_its_hold_time():
    p = jaxtraffic.TrafficParams(**SMALL, alpha_noise=0.15)
    a = np.asarray(noise_alpha_sequence(p, jax.random.PRNGKey(1), 23, NoiseReading(hold_steps=5)))
    assert a.shape == (23,)
    blocks = [a[i:i + 5] for i in range(0, 23, 5)]
    assert all(np.all(b == b[0]) for b in blocks)
    assert len({float(b[0]) for b in blocks}) == len(blocks)  # a new draw per hold period
    assert np.all((a >= 0) & (a <= 1))


def test_per_node_noise_differs_between_nodes_and_runs():
    p = jaxtraffic.TrafficParams(**SMALL, alpha_noise=0.15, delay=1.0)
    reading = NoiseReading(hold_steps=4, per_node=True)
    a = np.asarray(noise_alpha_sequence(p, jax.random.PRNGKey(1), 10, reading))
    assert a.shape == (10, p.n_points)
    assert np.all(a[:4] == a[0]) and np.unique(a[0]).size > p.n_points // 2
    res = jaxtraffic.simulate(p, jaxtraffic.backstepping(1.0, 1.0), n_steps=40,
                              alpha_input=jaxtraffic.AlphaInput(noise=reading), record=jaxtraffic.Record(every=10))
    assert not bool(res.metrics["diverged"]) and np.isfinite(float(res.metrics["J_comfort"]))
    with pytest.raises(ValueError):
        NoiseReading(per_node=True, model_sees=True)
    with pytest.raises(ValueError):
        NoiseReading(hold_steps=0)


def _spy() -> Controller:
    """Open loop that keeps the nominal alpha it was handed as its state."""
    def act(settings, cstate, obs, nominal, key):
        return jnp.full_like(obs.rho, nominal.h_bar), jnp.asarray(nominal.alpha, obs.rho.dtype)
    return Controller(settings=(), act_fn=act, init_fn=lambda s, o, n: jnp.asarray(0.0, o.rho.dtype), name="spy")


def test_model_sees_noise_controller_gets_the_plant_alpha():
    p = jaxtraffic.TrafficParams(**SMALL, alpha_noise=0.15, delay=1.0)
    rho0, v0 = jaxtraffic.paper_initial_condition(p)
    st = initial_state(p, rho0, v0)
    target = jaxtraffic.equilibrium(p)
    for sees, expected in ((True, 0.37), (False, 0.15)):
        _, cst, _, _ = closed_loop_step(st, jnp.asarray(0.0), _spy(), p, p, jnp.asarray(0.37), jax.random.PRNGKey(0),
                                        target, model_sees_noise=sees)
        np.testing.assert_allclose(float(cst), expected, rtol=1e-6)
    # through simulate: the last step's model alpha is the plant's last alpha
    key = jax.random.PRNGKey(4)
    reading = NoiseReading(hold_steps=3, model_sees=True)
    res = jaxtraffic.simulate(p, _spy(), n_steps=16, key=key, alpha_input=jaxtraffic.AlphaInput(noise=reading))
    alphas = noise_alpha_sequence(p, jax.random.split(key)[0], 16, reading)
    assert float(res.controller_state) == float(alphas[-1]) != 0.15


def test_given_alphas_reproduce_the_drawn_readings():
    """``alphas=plant_alphas(params, key, n, reading)`` reproduces the rollout that draws that reading
    (held road-wide, per node), so a batch of different holding times can share one program; the
    batch version matches its members; a reading that draws and given alphas do not combine."""
    p = jaxtraffic.TrafficParams(**SMALL, delay=1.0, max_delay_steps=8, alpha_noise=0.15)
    ctrl, n, key = jaxtraffic.backstepping(1.0, 1.0), 40, jax.random.PRNGKey(3)
    held, node = NoiseReading(hold_steps=7), NoiseReading(hold_steps=5, per_node=True)
    for reading in (None, held, node):
        drawn = jaxtraffic.simulate(p, ctrl, n_steps=n, key=key, alpha_input=jaxtraffic.AlphaInput(noise=reading))
        given_alphas = jaxtraffic.AlphaInput(alphas=jaxtraffic.plant_alphas(p, key, n, reading))
        given = jaxtraffic.simulate(p, ctrl, n_steps=n, key=key, alpha_input=given_alphas)
        assert float(drawn.metrics["J_comfort"]) > 0.0
        for k in ("J_TTT", "J_comfort", "final_rho_L2"):
            np.testing.assert_allclose(float(given.metrics[k]), float(drawn.metrics[k]), rtol=1e-6)
    keys = jax.random.split(key, 2)
    alphas = jnp.stack([jaxtraffic.plant_alphas(p, keys[0], n), jaxtraffic.plant_alphas(p, keys[1], n, held)])
    batch = jaxtraffic.simulate_batch(p, ctrl, n_steps=n, keys=keys, alpha_input=jaxtraffic.AlphaInput(alphas=alphas))
    for i, reading in enumerate((None, held)):
        one = jaxtraffic.simulate(p, ctrl, n_steps=n, key=keys[i], alpha_input=jaxtraffic.AlphaInput(noise=reading))
        np.testing.assert_allclose(float(batch.metrics["J_comfort"][i]), float(one.metrics["J_comfort"]), rtol=1e-5)
    with pytest.raises(ValueError, match="replaces the drawn"):
        jaxtraffic.simulate(p, ctrl, n_steps=n, alpha_input=jaxtraffic.AlphaInput(noise=held, alphas=alphas[1]))
    with pytest.raises(ValueError, match="shape"):
        jaxtraffic.simulate(p, ctrl, n_steps=n, alpha_input=jaxtraffic.AlphaInput(alphas=alphas[1][:-1]))
    with pytest.raises(ValueError, match="shape"):
        jaxtraffic.simulate_batch(p, ctrl, n_steps=n, keys=keys,
                                  alpha_input=jaxtraffic.AlphaInput(alphas=alphas[:, :-1]))
