"""Batched rollouts (docs/model.md sections 3-5, 10): determinism, divergence containment, open-loop
growth, metrics at equilibrium, one compile for many delays."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL, leaves_equal, take

import jaxtraffic
from jaxtraffic import (
    Controller,
    TrafficParams,
    cfl_number,
    equilibrium,
    equilibrium_state,
    lyapunov,
    paper_initial_condition,
    simulate,
    simulate_batch,
    stack_params,
)
from jaxtraffic.model.solver import is_physical
from jaxtraffic.sim import Memory, Record
from jaxtraffic.sim import metrics as sim_metrics
from jaxtraffic.sim.plant import closed_loop_step, initial_state, plant_alpha_sequence, select_state

SENTINELS = ("time_to_reward_target_s", "diverged_at_s")  # documented inf = "never"


def _finite_except_sentinels(metrics: dict) -> None:
    for k, x in metrics.items():
        x = np.asarray(x)
        if k in SENTINELS:
            assert not np.any(np.isnan(x)), k
            assert np.all(np.isfinite(x) | (x == np.inf)), k
        else:
            assert np.all(np.isfinite(x)), k


def _all_finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree)
               if np.issubdtype(np.asarray(x).dtype, np.floating))


# ----------------------------------------------------------------------------- determinism
def test_same_key_same_result_with_alpha_noise():
    p = TrafficParams(**SMALL, alpha_noise=0.05)
    k1, k2 = jax.random.PRNGKey(1), jax.random.PRNGKey(2)
    a = simulate(p, n_steps=200, key=k1, record=Record(every=10))
    b = simulate(p, n_steps=200, key=k1, record=Record(every=10))
    c = simulate(p, n_steps=200, key=k2, record=Record(every=10))
    assert leaves_equal(a, b)
    assert not np.array_equal(np.asarray(a.final.v), np.asarray(c.final.v))
    assert float(a.metrics["J_TTT"]) != float(c.metrics["J_TTT"])
    _finite_except_sentinels(a.metrics)


def test_without_noise_the_key_does_not_matter():
    p = TrafficParams(**SMALL)
    a = simulate(p, n_steps=200, key=jax.random.PRNGKey(1), record=Record(every=10))
    b = simulate(p, n_steps=200, key=jax.random.PRNGKey(2), record=Record(every=10))
    assert leaves_equal(a.metrics, b.metrics) and leaves_equal(a.final, b.final)


def test_batched_keys_are_reproducible_and_independent():
    p = TrafficParams(**SMALL, alpha_noise=0.05)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    a = simulate_batch(p, n_steps=200, keys=keys, record=Record(every=10))
    b = simulate_batch(p, n_steps=200, keys=keys, record=Record(every=10))
    assert leaves_equal(a, b)
    v = np.asarray(a.final.v)
    assert not np.array_equal(v[0], v[1]) and not np.array_equal(v[1], v[2])
    # a batch member equals the single rollout with the same key (to rounding)
    single = simulate(p, n_steps=200, key=keys[1], record=Record(every=10))
    np.testing.assert_allclose(v[1], single.final.v, rtol=1e-5)
    np.testing.assert_allclose(a.metrics["J_comfort"][1], single.metrics["J_comfort"], rtol=1e-4)


# ----------------------------------------------------------------------------- divergence
def _ic_batch(p: TrafficParams, amplitudes):
    return jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(jnp.asarray(amplitudes))


@pytest.mark.parametrize("bad_amplitude", [0.03, 0.09])
def test_divergence_is_contained(bad_amplitude):
    """One diverging environment leaves the others bit-identical; it is flagged and frozen at a
    finite, physical state; nothing non-finite appears anywhere but in the inf sentinels.
    Amplitude 0.03 leaves the physical region after ~10 s, 0.09 in the very first step."""
    p = TrafficParams(**SMALL)
    n_steps = 200
    healthy = [0.010, 0.005, 0.008]
    sick = [0.010, bad_amplitude, 0.008]
    ra, va = _ic_batch(p, healthy)
    rb, vb = _ic_batch(p, sick)
    A = simulate_batch(p, n_steps=n_steps, rho0=ra, v0=va, record=Record(every=10))
    B = simulate_batch(p, n_steps=n_steps, rho0=rb, v0=vb, record=Record(every=10))
    # the other environments: exactly the same results
    for i in (0, 2):
        assert leaves_equal(take(A, i), take(B, i)), f"env {i} changed"
    # flags
    assert not np.any(np.asarray(A.metrics["diverged"]))
    np.testing.assert_array_equal(np.asarray(B.metrics["diverged"]), [False, True, False])
    t_div = float(B.metrics["diverged_at_s"][1])
    assert 0.0 <= t_div < n_steps * float(p.dt)
    assert np.all(np.asarray(A.metrics["diverged_at_s"]) == np.inf)
    assert float(B.metrics["time_to_reward_target_s"][1]) == np.inf
    # finite everywhere (states, buffers, trajectories, metrics but the sentinels)
    assert _all_finite(B.final) and _all_finite(B.trajectory) and _all_finite(B.controller_state)
    _finite_except_sentinels(B.metrics)
    # the diverged environment is frozen at a physical state from its divergence on
    fin = take(B.final, 1)
    assert bool(is_physical(fin.rho, fin.v, p))
    rec = np.asarray(B.trajectory.rho[1])  # every 10th step
    k = int(np.ceil(t_div / (10 * float(p.dt)))) + 1
    for j in range(k, rec.shape[0]):
        np.testing.assert_array_equal(rec[j], np.asarray(fin.rho))
    assert int(fin.step) == n_steps


def test_divergence_by_extreme_parameter_is_contained():
    """Same with a batch of parameters: one plant (no ACC, manual relaxation time 1 s instead
    of 60 s) leaves the physical region after ~30 s."""
    n_steps = 200
    kw = {"n_points": SMALL["n_points"], "dt": [SMALL["dt"]] * 3}
    ra, va = _ic_batch(TrafficParams(**SMALL), [0.01, 0.01, 0.008])
    pa = stack_params(alpha=[0.15, 0.15, 0.15], **kw)
    pb = stack_params(alpha=[0.15, 0.0, 0.15], tau_m=[60.0, 1.0, 60.0], **kw)
    A = simulate_batch(pa, n_steps=n_steps, rho0=ra, v0=va)
    B = simulate_batch(pb, n_steps=n_steps, rho0=ra, v0=va)
    np.testing.assert_array_equal(np.asarray(B.metrics["diverged"]), [False, True, False])
    for i in (0, 2):
        assert leaves_equal(take(A, i), take(B, i))
    assert _all_finite(B.final)
    _finite_except_sentinels(B.metrics)


def test_non_physical_initial_state_is_rejected_clearly():
    p = TrafficParams(**SMALL)
    rho, v = equilibrium_state(p)
    with pytest.raises(ValueError, match="physical region"):
        simulate(p, n_steps=10, rho0=rho.at[3].set(-0.01), v0=v)
    with pytest.raises(ValueError, match=r"environment\(s\) \[1\]"):
        simulate_batch(p, n_steps=10, rho0=jnp.stack([rho, rho.at[0].set(jnp.nan)]), v0=jnp.stack([v, v]))


def test_traced_non_physical_initial_state_is_flagged_not_spread():
    """Inside a user's jit the initial state cannot be checked: it is flagged at step 0, its
    metrics stay finite and the other environments are untouched."""
    p = TrafficParams(**SMALL)
    rho, v = equilibrium_state(p)
    r0 = jnp.stack([rho, rho.at[5].set(jnp.nan), rho])
    v0 = jnp.stack([v, v, v.at[2].set(-1.0)])

    @jax.jit
    def go(r0, v0):
        return simulate_batch(p, n_steps=200, rho0=r0, v0=v0, record=Record(every=10))

    res = go(r0, v0)
    np.testing.assert_array_equal(np.asarray(res.metrics["diverged"]), [False, True, True])
    np.testing.assert_array_equal(np.asarray(res.metrics["diverged_at_s"])[1:], [0.0, 0.0])
    for k in ("J_TTT", "J_fuel", "J_comfort", "control_effort", "max_cfl"):
        assert np.all(np.isfinite(np.asarray(res.metrics[k]))), k
    np.testing.assert_array_equal(np.asarray(res.metrics["J_TTT"])[1:], [0.0, 0.0])


# ----------------------------------------------------------------------------- open loop (paper grid)
@pytest.fixture(scope="module")
def paper_open_loop():
    p = TrafficParams()
    rho0, v0 = paper_initial_condition(p)
    return simulate(p, n_steps=3000, rho0=rho0, v0=v0, record=Record(every=10))


def test_open_loop_from_paper_ic_grows(paper_open_loop):
    res = paper_open_loop
    t = np.asarray(res.trajectory.t)
    l2 = np.asarray(res.trajectory.rho_L2)
    assert t[0] == 0.0 and t[-1] == pytest.approx(299.0) and l2.shape == (300,)
    # an initial transient decays first ...
    i_min = int(np.argmin(l2[t <= 100.0]))
    assert l2[i_min] < 0.8 * l2[0]
    # ... then the density deviation grows through 300 s
    late = l2[(t >= 100.0)]
    assert late[-1] > 1.5 * l2[i_min] and late[-1] > l2[0]
    assert np.corrcoef(t[t >= 100.0], late)[0, 1] > 0.9
    assert float(res.metrics["J_TTT"]) > 3.2208e7
    assert not bool(res.metrics["diverged"])
    assert float(res.metrics["time_to_reward_target_s"]) == np.inf
    _finite_except_sentinels(res.metrics)


def test_metrics_at_equilibrium_paper_grid():
    """docs/model.md section 10: J_TTT = 3.2208e7 and J_fuel = 8.077e5 over 300 s at equilibrium."""
    p = TrafficParams()
    rho0, v0 = equilibrium_state(p)
    res = simulate(p, n_steps=3000, rho0=rho0, v0=v0, record=Record(every=10))
    m = res.metrics
    rho_bar, v_bar = (float(x) for x in equilibrium(p))
    assert float(m["J_TTT"]) == pytest.approx(3.2208e7, rel=5e-5)
    # float32 streaming sums over 3000 steps: ~1e-5 relative rounding
    assert float(m["J_TTT"]) == pytest.approx(1000.0 * rho_bar * 1000.0 * 300.0, rel=5e-5)
    assert float(m["J_fuel"]) == pytest.approx(8.077e5, rel=1e-4)
    xi = sim_metrics.FUEL_B0 + sim_metrics.FUEL_B1 * v_bar + sim_metrics.FUEL_B3 * v_bar**3
    assert float(m["J_fuel"]) == pytest.approx(xi * 1000.0 * rho_bar * 1000.0 * 300.0, rel=5e-5)
    assert 0.0 <= float(m["J_comfort"]) < 1e-3
    assert float(m["final_rho_L2"]) < 1e-3 and float(m["final_v_L2"]) < 1e-4  # veh/km, m/s
    assert float(m["time_to_reward_target_s"]) == 0.0
    assert float(m["control_effort"]) == 0.0
    assert float(m["max_cfl"]) == pytest.approx(cfl_number(p), rel=1e-4)
    assert not bool(m["diverged"]) and float(m["diverged_at_s"]) == np.inf


def test_metrics_scale_with_horizon_and_match_trajectory():
    """J_TTT over 30 s on a small grid is 1/10 of the 300 s value; the streamed J_TTT equals the
    space-trapezoid / time-rectangle sum of the recorded density (record_every=1)."""
    p = TrafficParams(**SMALL)
    rho0, v0 = equilibrium_state(p)
    res = simulate(p, n_steps=60, rho0=rho0, v0=v0, record=Record(every=1))
    assert float(res.metrics["J_TTT"]) == pytest.approx(3.2208e6, rel=5e-5)
    rho_bar, v_bar = equilibrium(p)
    rho, v = paper_initial_condition(p, amplitude=0.008)
    res = simulate(p, n_steps=60, rho0=rho, v0=v, record=Record(every=1))
    tr = res.trajectory
    rec = np.asarray(tr.rho, np.float64) * 1000.0
    dx, dt = float(p.dx), float(p.dt)
    j_ttt = dt * np.sum(dx * (rec.sum(axis=1) - 0.5 * (rec[:, 0] + rec[:, -1])))
    assert float(res.metrics["J_TTT"]) == pytest.approx(j_ttt, rel=1e-5)
    np.testing.assert_allclose(tr.reward, sim_metrics.reward(tr.rho, tr.v, rho_bar, v_bar, p.dx), rtol=1e-6)
    np.testing.assert_allclose(tr.t, np.arange(60) * dt, rtol=1e-6)


# ----------------------------------------------------------------------------- batches of delays
_TRACES = {"n": 0}


def _counting_lyapunov_act(settings, cstate, obs, nominal, key):
    _TRACES["n"] += 1  # Python side effect: runs once per trace, not per step
    return lyapunov().act_fn(settings, cstate, obs, nominal, key)


def test_batch_of_delays_matches_separate_runs_with_one_compile():
    base = TrafficParams(**SMALL)
    ctrl = Controller(settings=lyapunov().settings, act_fn=_counting_lyapunov_act, name="counting")
    rho0, v0 = paper_initial_condition(base)
    n_steps = 200
    delays = [0.0, 1.0, 2.5, 4.0]
    res = simulate_batch(stack_params(delay=delays, **SMALL), ctrl, n_steps=n_steps, rho0=rho0, v0=v0)
    traces = _TRACES["n"]
    assert traces >= 1
    # another batch of delays (same batch size): served by the same compiled program
    res2 = simulate_batch(stack_params(delay=[0.5, 3.0, 0.0, 1.5], **SMALL), ctrl, n_steps=n_steps,
                          rho0=rho0, v0=v0)
    assert _TRACES["n"] == traces, "a new batch of delays recompiled the rollout"
    np.testing.assert_array_equal(np.asarray(res2.metrics["J_TTT"])[2], np.asarray(res.metrics["J_TTT"])[0])
    for i, d in enumerate(delays):
        single = simulate(base.replace(delay=d), ctrl, n_steps=n_steps, rho0=rho0, v0=v0)
        for k in ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "control_effort"):
            np.testing.assert_allclose(res.metrics[k][i], single.metrics[k], rtol=2e-5, err_msg=f"{k} D={d}")
        np.testing.assert_allclose(res.final.rho[i], single.final.rho, rtol=1e-5)
        np.testing.assert_allclose(res.final.v[i], single.final.v, rtol=1e-5)
    # the delays really matter
    effort = np.asarray(res.metrics["final_rho_L2"])
    assert len(set(np.round(effort, 7).tolist())) == len(delays)


def test_simulate_batch_input_checks():
    p = TrafficParams(**SMALL)
    with pytest.raises(ValueError, match="nothing is batched"):
        simulate_batch(p, n_steps=10)
    with pytest.raises(ValueError, match="multiple of record_every"):
        simulate(p, n_steps=10, record=Record(every=3))
    rho, v = equilibrium_state(p)
    with pytest.raises(ValueError, match="both rho0 and v0"):
        simulate(p, n_steps=10, rho0=rho)


def test_chunked_batches_match_one_vmap_and_contain_divergence():
    """simulate_batch in chunks (here 2 environments per chunk, 5 environments: padded to 6)
    gives the one-vmap results, and a diverging environment still leaves the others untouched."""
    p = TrafficParams(**SMALL)
    amps = [0.010, 0.005, 0.008, 0.006, 0.009]
    r0, v0 = _ic_batch(p, amps)
    ctrl = lyapunov(jnp.asarray([1.0, 0.5, 1.5, 1.0, 0.8]))
    kw = {"n_steps": 200, "record": Record(every=10), "batch_controller": True}
    one = simulate_batch(p, ctrl, rho0=r0, v0=v0, memory=Memory(chunk_size=None), **kw)
    chunked = simulate_batch(p, ctrl, rho0=r0, v0=v0, memory=Memory(chunk_size=2), **kw)
    assert np.asarray(chunked.final.rho).shape == (5, p.n_points)
    assert np.asarray(chunked.trajectory.rho).shape == (5, 20, p.n_points)
    # (two programs: float32 rounding may differ, e.g. 3e-8 on a reward of -1.6e-3 over 200 steps)
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(chunked), strict=True):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=1e-5, atol=1e-7)
    # env 3 diverges (open-loop-like gain, huge amplitude); the others: bit-identical
    r_bad, v_bad = _ic_batch(p, [0.010, 0.005, 0.008, 0.09, 0.009])
    sick = simulate_batch(p, ctrl, rho0=r_bad, v0=v_bad, memory=Memory(chunk_size=2), **kw)
    np.testing.assert_array_equal(np.asarray(sick.metrics["diverged"]), [False, False, False, True, False])
    for i in (0, 1, 2, 4):
        assert leaves_equal(take(chunked, i), take(sick, i)), f"env {i} changed"
    assert _all_finite(sick.final)
    _finite_except_sentinels(sick.metrics)


def test_time_to_reward_target_matches_the_recorded_rewards():
    """time_to_reward_target_s is the time after which the reward stays >= -0.1, checked against
    the per-step rewards of the trajectory (record_every=1) for a stabilising controller."""
    p = TrafficParams(**SMALL)
    rho0, v0 = paper_initial_condition(p)
    res = simulate(p, lyapunov(), n_steps=200, rho0=rho0, v0=v0, record=Record(every=1))
    r = np.append(np.asarray(res.trajectory.reward), float(res.metrics["final_reward"]))
    bad = np.flatnonzero(r < sim_metrics.REWARD_TARGET)
    assert r[0] < sim_metrics.REWARD_TARGET and r[-1] >= sim_metrics.REWARD_TARGET  # it really crosses the target
    expected = (bad[-1] + 1) * float(p.dt)
    assert float(res.metrics["time_to_reward_target_s"]) == pytest.approx(expected)
    assert 0.0 < expected < 200 * float(p.dt)


def test_simulate_is_a_scan_of_closed_loop_step():
    """``simulate`` is exactly ``closed_loop_step`` iterated (with the plant alphas drawn up front)."""
    p = jaxtraffic.TrafficParams(**SMALL, delay=0.5, alpha_noise=0.05)
    ctrl = jaxtraffic.backstepping(0.5, 1.0)
    n_steps = 30
    key = jax.random.PRNGKey(5)
    res = jaxtraffic.simulate(p, ctrl, n_steps=n_steps, key=key)
    k_plant, k_ctrl = jax.random.split(key)
    rho0, v0 = jaxtraffic.paper_initial_condition(p)
    target = jaxtraffic.equilibrium(p)
    alphas = plant_alpha_sequence(p, k_plant, n_steps, rho0.dtype)

    @jax.jit
    def run(alphas):
        def body(carry, a):
            plant, cstate = carry
            plant, cstate, h, info = closed_loop_step(plant, cstate, ctrl, p, p, a,
                                                      jax.random.fold_in(k_ctrl, plant.step), target)
            return (plant, cstate), (h, info.reward)

        state = initial_state(p, rho0, v0)
        return jax.lax.scan(body, (state, ctrl.init(state.observation(p), p)), alphas)

    (plant, _), (hs, rewards) = run(alphas)
    np.testing.assert_allclose(plant.rho, res.final.rho, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(plant.v, res.final.v, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(hs[-1], res.final.h_prev, rtol=1e-6)
    np.testing.assert_allclose(rewards[-1], res.metrics["final_reward"], rtol=1e-4)


def test_select_state_restarts_without_copying_the_buffer():
    """``select_state(done, initial_state(..., sent=s.sent), s)``: the fresh state where done, the old
    one elsewhere; the buffer storage is the old one's either way (only its bookkeeping switches)."""
    p = jaxtraffic.TrafficParams(**SMALL, delay=1.5)
    rho0, v0 = jaxtraffic.paper_initial_condition(p)
    s = initial_state(p, rho0, v0)
    for _ in range(5):
        s, _, _, _ = closed_loop_step(s, (), jaxtraffic.constant_gains(0.0, 0.0, 1.0), p, p, p.alpha,
                                      jax.random.PRNGKey(0), jaxtraffic.equilibrium(p))
    fresh = initial_state(p, rho0 * 1.01, q := p.q_in / (rho0 * 1.01), sent=s.sent)
    kept, reset = select_state(jnp.asarray(False), fresh, s), select_state(jnp.asarray(True), fresh, s)
    assert leaves_equal(kept, s)
    np.testing.assert_array_equal(reset.rho, fresh.rho)
    np.testing.assert_array_equal(reset.v, q)
    assert int(reset.step) == 0 and int(reset.sent.valid) == 0 and int(kept.sent.valid) == 5
    np.testing.assert_array_equal(reset.sent.data, s.sent.data)
