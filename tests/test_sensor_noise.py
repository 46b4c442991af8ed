"""Sensor noise (jaxtraffic.control.noise, issue 47 item 2): what the law sees (the relative error's mean, standard
deviation, independence and seeding), a level of 0 as the law itself, a batch of levels, the scenario
distribution's draw of it (the other draws untouched), and the comparison under it: the same values in any chunk
order, and the filtered law less hurt than the pointwise one, as its filter's theory says."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.compare import LawSpec, ScenarioDistribution, evaluate_laws, sample
from jaxtraffic.control import Controller, Observation, measurement_filter, sensor_noise, tell_delay
from jaxtraffic.model import delay as delay_buffer

TINY = jt.TrafficParams(n_points=21, dt=0.5, max_delay_steps=20)


def _seen(settings, cstate, obs, nominal, key):
    """A probe law: it returns the density it sees as its "time gap" (shape (n,))."""
    return obs.rho, cstate


def _obs(n: int, rho: float = 0.04, v: float = 10.0) -> Observation:
    h = jnp.full((n,), 1.0)
    return Observation(rho=jnp.full((n,), rho), v=jnp.full((n,), v), h_prev=h, t=jnp.zeros(()),
                       sent=delay_buffer.init_buffer(h, 2))


def test_the_law_sees_each_node_with_the_relative_error_of_its_level():
    probe = Controller(settings=jnp.zeros(()), act_fn=_seen)
    obs, nominal, key = _obs(20_000), jt.TrafficParams(), jax.random.PRNGKey(7)
    seen, _ = sensor_noise(probe, 0.05).act((), obs, nominal, key)
    rel = np.asarray(seen) / 0.04 - 1.0
    assert abs(rel.mean()) < 3 * 0.05 / np.sqrt(rel.size)  # unbiased
    assert rel.std() == pytest.approx(0.05, rel=0.03)
    assert abs(np.corrcoef(rel[:-1], rel[1:])[0, 1]) < 0.03  # independent from node to node
    again, _ = sensor_noise(probe, 0.05).act((), obs, nominal, key)
    np.testing.assert_array_equal(np.asarray(again), np.asarray(seen))  # seeded
    other, _ = sensor_noise(probe, 0.05).act((), obs, nominal, jax.random.PRNGKey(8))
    assert not np.allclose(np.asarray(other), np.asarray(seen))
    zero, _ = sensor_noise(probe, 0.0).act((), obs, nominal, key)
    np.testing.assert_array_equal(np.asarray(zero), np.asarray(obs.rho))
    for bad in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="sensor noise level"):
            sensor_noise(probe, bad)


def test_level_zero_is_the_law_itself_and_a_batch_of_levels_is_one_program():
    p = TINY.replace(delay=2.0)
    law = tell_delay(measurement_filter(jt.backstepping(1.0), 25.0, dx=float(p.dx)), 2.0)
    own = jt.simulate(p, law, n_steps=80)
    quiet = jt.simulate(p, sensor_noise(law, 0.0), n_steps=80)
    for k in ("final_rho_L2", "J_comfort"):
        assert float(quiet.metrics[k]) == pytest.approx(float(own.metrics[k]), rel=1e-5), k  # (compiled apart)
    levels = jnp.asarray([0.0, 0.02, 0.1])
    batch = jt.simulate_batch(jt.stack_params(p, p, p), sensor_noise(law, levels), n_steps=80, batch_controller=True,
                              keys=jax.random.split(jax.random.PRNGKey(0), 3))
    assert float(batch.metrics["final_rho_L2"][0]) == pytest.approx(float(own.metrics["final_rho_L2"]), rel=1e-5)
    assert len(set(np.asarray(batch.metrics["J_comfort"]).round(6))) == 3
    assert float(batch.metrics["J_comfort"][2]) > float(batch.metrics["J_comfort"][0])  # noise costs comfort


def test_the_distribution_draws_a_level_per_scenario_and_leaves_the_other_draws_alone():
    plain = sample(ScenarioDistribution(), "test", 32, seed=1, base=TINY)
    noisy = sample(ScenarioDistribution(sensor_noise_range=(0.01, 0.05)), "test", 32, seed=1, base=TINY)
    for k, v in plain.draws.items():
        if k != "sensor_noise":
            np.testing.assert_array_equal(noisy.draws[k], v, err_msg=k)
    np.testing.assert_array_equal(plain.draws["sensor_noise"], 0.0)
    lv = noisy.draws["sensor_noise"]
    assert 0.01 <= lv.min() and lv.max() <= 0.05 and np.ptp(lv) > 0.02
    with pytest.raises(ValueError, match="sensor_noise_range"):
        ScenarioDistribution(sensor_noise_range=(0.0, 1.5))


def test_the_comparison_under_noise_is_order_free_and_the_filter_rejects_it():
    """Each scenario's noise is its own (keyed by its index): the same values whatever the chunks' order. White
    measurement noise reaches the pointwise backstepping law whole and the filtered one (50 m: one node of this
    grid) attenuated, so the noise raises the pointwise law's time-gap chatter (J_comfort) by more than the
    filtered law's."""
    dist = ScenarioDistribution(sensor_noise_range=(0.02, 0.02))
    scen, clean = sample(dist, "test", 8, seed=2, base=TINY), sample(ScenarioDistribution(), "test", 8, 2, TINY)
    dx = float(TINY.dx)
    laws = [LawSpec("pointwise", "backstepping", lambda: jt.backstepping(4.0), told="delay"),
            LawSpec("filtered", "backstepping, filter", lambda: measurement_filter(jt.backstepping(4.0), 50.0, dx=dx),
                    told="delay")]
    run = {b: evaluate_laws(laws, scen, TINY, horizon_s=60.0, chunk=4, log=lambda s: None, by_delay=b) for b in
           (True, False)}
    for law in run[True]:
        for k, v in run[False][law].items():
            np.testing.assert_array_equal(run[True][law][k], v, err_msg=(law, k))
    base = evaluate_laws(laws, clean, TINY, horizon_s=60.0, chunk=4, log=lambda s: None)
    with np.errstate(invalid="ignore"):  # inf / inf where a rollout diverged on the coarse tiny grid
        rise = {n: run[True][n]["J_comfort"] / base[n]["J_comfort"] for n in ("pointwise", "filtered")}
    both = np.isfinite(rise["pointwise"]) & np.isfinite(rise["filtered"])
    assert both.sum() >= 3
    assert np.all(rise["pointwise"][both] > rise["filtered"][both]) and np.all(rise["filtered"][both] > 1.5)
