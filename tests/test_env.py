"""The gymnax-style gain environment (jaxtraffic/learn/env.py) on a tiny grid (21 nodes, dt = 0.1 s)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic.control import gain_policy as gp
from jaxtraffic.learn import env as learn_env
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.sim import equilibrium_state, initial_state
from jaxtraffic.sim.metrics import reward as paper_reward

N = 21
TP = TrafficParams(n_points=N, delay=0.5)

step_jit = jax.jit(learn_env.step)
reset_jit = jax.jit(learn_env.reset)
reset_batch = jax.jit(jax.vmap(learn_env.reset, (0, None)))
KEYS = jax.random.split(jax.random.PRNGKey(7), 400)


def _params(**kw) -> learn_env.EnvParams:
    """The paper's environment (full observation, one gain bound, gains applied directly, the paper's
    reward) unless ``kw`` says otherwise."""
    kw.setdefault("horizon", 20)
    kw.setdefault("gain_max", 5.0)
    kw.setdefault("gain_filter", 1.0)
    kw.setdefault("h_rate_weight", 0.0)
    kw.setdefault("wave_weight", 0.0)
    kw.setdefault("obs_segments", 0)
    return learn_env.make_env_params(TP, **kw)


def test_reset_step_shapes_and_reward():
    ep = _params()
    obs, st = reset_jit(jax.random.PRNGKey(0), ep)
    assert obs.shape == (3 * N + 3,) == (learn_env.obs_size(ep),)
    np.testing.assert_array_equal(obs[3 * N:], 0.0)  # no gains applied yet
    assert learn_env.TrafficEnv.action_size == 3
    assert int(st.t) == 0 and st.plant.rho.shape == (N,)
    obs2, st2, r, done, info = step_jit(jax.random.PRNGKey(1), st, jnp.array([0.3, -0.2, 0.1]), ep)
    assert obs2.shape == (3 * N + 3,) and r.shape == () and done.shape == () and done.dtype == jnp.bool_
    assert info["terminal_obs"].shape == (3 * N + 3,) and info["gains"].shape == (3,)
    np.testing.assert_allclose(obs2[3 * N:], info["gains"] / ep.gain_max, rtol=1e-6)
    assert info["truncated"].dtype == jnp.bool_ and info["terminated"].dtype == jnp.bool_
    assert int(st2.t) == 1 and not bool(done)
    # no reset: obs is the new state's (equal up to XLA fusion rounding)
    np.testing.assert_allclose(obs2, info["terminal_obs"], rtol=0, atol=1e-6)
    # reward: the paper's r of the state after the step = -(dx/5) sum(rho~^2 + v~^2) of the normalised obs
    rho_bar, v_bar = equilibrium(TP)
    np.testing.assert_allclose(r, paper_reward(st2.plant.rho, st2.plant.v, rho_bar, v_bar, TP.dx), rtol=1e-6)
    np.testing.assert_allclose(r, -np.sum(np.asarray(obs2[: 2 * N]) ** 2) * float(TP.dx) / 5.0, rtol=1e-4)
    assert float(r) < 0.0


def test_pooled_observation_averages_segments():
    """obs_segments K: each normalised field is averaged over K equal road segments; one bound per gain."""
    ep = _params(obs_segments=4, gain_max=(1.0, 3.0, 3.0))
    assert learn_env.obs_size(ep) == 3 * 4 + 3 and ep.gain_max == (1.0, 3.0, 3.0)
    obs, st = reset_jit(jax.random.PRNGKey(0), ep)
    full = np.asarray(gp.policy_features(st.plant.observation(TP), st.gains, TP, 1.0))[:3 * N].reshape(3, N)
    idx = np.minimum(np.arange(N) * 4 // (N - 1), 3)
    expected = np.stack([[full[f, idx == k].mean() for k in range(4)] for f in range(3)]).reshape(-1)
    np.testing.assert_allclose(obs[:12], expected, rtol=1e-5, atol=1e-7)
    _, _, _, _, info = step_jit(jax.random.PRNGKey(1), st, jnp.array([5.0, 5.0, -5.0]), ep)
    np.testing.assert_allclose(info["gains"], np.tanh([5.0, 5.0, -5.0]) * [1.0, 3.0, 3.0], rtol=1e-5)
    with pytest.raises(ValueError, match="obs_segments"):
        _params(obs_segments=N + 1)
    with pytest.raises(ValueError, match="gain_max"):
        _params(gain_max=(1.0, 0.0, 3.0))


def test_equilibrium_gives_zero_observation_and_stays():
    rho, v = equilibrium_state(TP)
    plant = initial_state(TP, rho, v)
    state = learn_env.EnvState(plant=plant, plant_params=TP, t=jnp.zeros((), jnp.int32), gains=jnp.zeros(3))
    np.testing.assert_allclose(learn_env.observe(state, _params()), np.zeros(3 * N + 3), atol=1e-6)
    # zero amplitude: reset is the equilibrium; zero gains keep it there with reward ~ 0
    ep = _params(amp_min=0.0, amp_max=0.0)
    obs, st = reset_jit(jax.random.PRNGKey(3), ep)
    np.testing.assert_allclose(obs, 0.0, atol=1e-6)
    obs2, _, r, done, _ = step_jit(jax.random.PRNGKey(4), st, jnp.zeros(3), ep)
    np.testing.assert_allclose(obs2, 0.0, atol=1e-5)
    assert abs(float(r)) < 1e-8 and not bool(done)
    # a perturbed state is not zero (normalisation by rho_bar: rho~/rho_bar)
    obs_p, st_p = reset_jit(jax.random.PRNGKey(3), _params())
    rho_bar, _ = equilibrium(TP)
    np.testing.assert_allclose(obs_p[:N], st_p.plant.rho / rho_bar - 1.0, rtol=1e-6, atol=1e-7)
    assert float(jnp.max(jnp.abs(obs_p[:N]))) > 0.05


def test_auto_reset_on_truncation():
    horizon = 3
    ep = _params(horizon=horizon)
    obs, st = reset_jit(jax.random.PRNGKey(0), ep)
    a = jnp.array([0.5, 0.5, -0.5])
    for i in range(1, horizon + 1):
        k = jax.random.PRNGKey(100 + i)
        obs, new, r, done, info = step_jit(k, st, a, ep)
        if i < horizon:
            assert not bool(done) and not bool(info["truncated"]) and int(new.t) == i
            np.testing.assert_allclose(obs, info["terminal_obs"], rtol=0, atol=1e-6)
        else:
            assert bool(done) and bool(info["truncated"]) and not bool(info["terminated"])
            assert int(new.t) == 0 and int(new.plant.step) == 0
            # the returned obs is a fresh episode's; terminal_obs is the last state of the old one
            obs_reset, st_reset = reset_jit(jax.random.split(k)[1], ep)
            np.testing.assert_allclose(obs, obs_reset, rtol=0, atol=1e-6)
            np.testing.assert_allclose(new.plant.rho, st_reset.plant.rho, rtol=1e-6)
            plant_before = st.plant
            assert not np.allclose(info["terminal_obs"], obs)
            assert int(plant_before.step) == horizon - 1
            assert np.isfinite(float(r)) and float(r) > -ep.diverge_penalty
        st = new


def test_diverged_env_terminates_with_penalty_and_resets():
    ep = _params(horizon=50)
    _, st = reset_jit(jax.random.PRNGKey(0), ep)
    bad = st.replace(plant=st.plant.replace(v=st.plant.v.at[N // 2].set(5000.0)))  # CFL >> 1: blows up
    obs, new, r, done, info = step_jit(jax.random.PRNGKey(1), bad, jnp.zeros(3), ep)
    assert bool(info["terminated"]) and not bool(info["truncated"]) and bool(done)
    assert float(r) == -ep.diverge_penalty
    assert int(new.t) == 0 and not bool(new.plant.diverged)  # reset to a fresh, physical episode
    assert np.all(np.isfinite(np.asarray(obs)))
    # truncation is never reported on the diverging step, even at the horizon
    at_horizon = bad.replace(t=jnp.asarray(ep.horizon - 1, bad.t.dtype))
    _, _, r2, _, info2 = step_jit(jax.random.PRNGKey(1), at_horizon, jnp.zeros(3), ep)
    assert bool(info2["terminated"]) and not bool(info2["truncated"]) and float(r2) == -ep.diverge_penalty


def test_domain_randomisation_ranges():
    ep = _params(delay_min=1.0, delay_max=3.0, alpha_min=0.1, alpha_max=0.3, amp_min=0.004, amp_max=0.012,
                 wavenumber_min=1, wavenumber_max=3, phase_max=2.0)
    obs, st = reset_batch(KEYS, ep)
    delay = np.asarray(st.plant_params.delay, np.float64)
    steps = delay / TP.dt
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-4)  # a multiple of dt
    assert delay.min() >= 1.0 - 1e-6 and delay.max() <= 3.0 + 1e-6
    assert len(np.unique(np.round(steps))) == 21  # every step count in [10, 30] is drawn
    alpha = np.asarray(st.plant_params.alpha)
    assert alpha.min() >= 0.1 and alpha.max() <= 0.3 and alpha.std() > 0.03
    # the plant's delay buffer uses the drawn delay
    np.testing.assert_array_equal(np.asarray(st.plant_params.delay_steps), np.round(steps).astype(int))
    # amplitude of the initial cosine in [amp_min, amp_max] (max over a grid <= the amplitude)
    rho_bar, _ = equilibrium(TP)
    amp = np.max(np.abs(np.asarray(obs[:, :N])), axis=1) * float(rho_bar)
    assert amp.max() <= 0.012 * (1 + 1e-4) and amp.min() > 0.0
    assert amp.max() > 0.011 and np.median(amp) < 0.010
    # nominal traffic params (the observation's normalisation) are unchanged
    assert float(ep.traffic.delay) == 0.5 and float(ep.traffic.alpha) == pytest.approx(0.15)


def test_no_randomisation_by_default():
    ep = _params()
    obs, st = reset_batch(KEYS, ep)
    np.testing.assert_allclose(st.plant_params.delay, 0.5)
    np.testing.assert_allclose(st.plant_params.alpha, 0.15)
    np.testing.assert_allclose(obs, np.broadcast_to(obs[0], obs.shape), atol=1e-7)  # the paper IC every time


def test_action_to_gains_bounded():
    ep = _params(gain_max=2.5)
    a = jnp.array([-1e6, -3.0, 0.0, 0.7, 40.0, 1e6])
    g = learn_env.action_to_gains(a, ep)
    assert float(jnp.max(jnp.abs(g))) <= 2.5
    np.testing.assert_allclose(g, 2.5 * np.tanh(np.asarray(a)), rtol=1e-6)
    assert float(g[0]) == -2.5 and float(g[-1]) == 2.5 and float(g[2]) == 0.0
    _, st = reset_jit(jax.random.PRNGKey(0), ep)
    _, _, _, _, info = step_jit(jax.random.PRNGKey(1), st, jnp.array([100.0, -100.0, 0.3]), ep)
    np.testing.assert_allclose(info["gains"], [2.5, -2.5, 2.5 * np.tanh(0.3)], rtol=1e-6)


@pytest.mark.parametrize("kw, match", [
    ({"alpha_min": 0.1, "alpha_max": 1.5}, "alpha"),
    ({"alpha_min": -0.1, "alpha_max": 0.5}, "alpha"),
    ({"alpha_min": -0.1, "alpha_max": 1.5}, "alpha"),
    ({"delay_min": 3.0, "delay_max": 2.0}, "delay_min"),
    ({"delay_min": 1.0, "delay_max": 20.0}, "buffer"),
    ({"horizon": 0}, "horizon"),
    ({"gain_filter": 0.0}, "gain_filter"),
    ({"gain_filter": 1.5}, "gain_filter"),
    ({"noise_min": 0.1, "noise_max": 0.05}, "noise_min"),
    ({"noise_max": 1.5}, "sensor noise"),
])
def test_make_env_params_rejects_bad_ranges(kw, match):
    with pytest.raises(ValueError, match=match):
        learn_env.make_env_params(TP, **kw)


def test_auto_reset_forgets_the_previous_episodes_inputs():
    """After an auto-reset the plant must receive h_bar for its first d steps, not the inputs the
    previous episode still had in flight (the reset restarts the buffer without rewriting it)."""
    from jaxtraffic.model import delay as delay_buffer

    tp = TrafficParams(n_points=21, L=500.0, delay=1.0, max_delay_steps=20)
    ep = learn_env.make_env_params(tp, horizon=15)
    d = int(round(1.0 / tp.dt))
    _, state = learn_env.reset(jax.random.PRNGKey(0), ep)
    step = jax.jit(learn_env.step)
    big = jnp.array([0.0, 0.0, 3.0])  # strong density feedback: sent h differs from h_bar
    for i in range(15):
        _, state, _, done, _ = step(jax.random.PRNGKey(i), state, big, ep)
    assert bool(done) and int(state.t) == 0
    sent = state.plant.sent
    # the old storage still holds the previous episode's (non-nominal) inputs ...
    assert float(jnp.max(jnp.abs(sent.data - tp.h_bar))) > 1e-3
    # ... but every delayed read of the new episode returns h_bar until d inputs have been sent
    for k in range(d + 1):
        np.testing.assert_array_equal(np.asarray(delay_buffer.read(sent, k)), np.full(21, tp.h_bar, np.float32))
    for i in range(d - 1):
        _, state, _, _, _ = step(jax.random.PRNGKey(100 + i), state, big, ep)
        np.testing.assert_array_equal(np.asarray(delay_buffer.read(state.plant.sent, d)),
                                      np.full(21, tp.h_bar, np.float32))
    # the newest entry is this episode's own input, not a stale one (to an ulp: XLA may recompute the
    # sent field in two fusions; stale inputs differ by > 1e-3, see above)
    np.testing.assert_allclose(np.asarray(delay_buffer.read(state.plant.sent, 0)), np.asarray(state.plant.h_prev),
                               rtol=1e-6)


def test_gain_filter_is_a_first_order_lag():
    """With gain_filter k and a constant action, the applied gains after n steps are
    target (1 - (1 - k)^n); k = 1 applies the policy's gains at once. A reset zeroes them."""
    k = 0.2
    ep = _params(gain_filter=k, horizon=8)
    _, st = reset_jit(jax.random.PRNGKey(0), ep)
    a = jnp.array([0.4, -0.7, 1.1])
    target = np.asarray(learn_env.action_to_gains(a, ep))
    for n in range(1, 8):
        obs, st, _, done, info = step_jit(jax.random.PRNGKey(n), st, a, ep)
        np.testing.assert_allclose(info["gains"], target * (1 - (1 - k) ** n), rtol=1e-5)
        np.testing.assert_allclose(obs[3 * N:], np.asarray(info["gains"]) / ep.gain_max, rtol=1e-6)
        assert not bool(done)
    # the state the plant received is the gain law with the *applied* gains, not the policy's
    obs, st, _, done, info = step_jit(jax.random.PRNGKey(9), st, a, ep)
    assert bool(done) and float(jnp.max(jnp.abs(st.gains))) == 0.0 and float(jnp.max(jnp.abs(obs[3 * N:]))) == 0.0
    _, _, _, _, info1 = step_jit(jax.random.PRNGKey(1), reset_jit(jax.random.PRNGKey(0), _params())[1], a, _params())
    np.testing.assert_allclose(info1["gains"], target, rtol=1e-6)


def _step_with_and_without(**penalty):
    """One step from a reset state with the paper's reward and with ``penalty``: (state before, state after,
    paper reward, penalised reward); checks that the penalty changes the reward only."""
    _, st = reset_jit(jax.random.PRNGKey(0), _params())
    a = jnp.array([0.2, 0.1, -0.3])
    _, st0, r0, _, _ = step_jit(jax.random.PRNGKey(1), st, a, _params())
    _, st1, r1, _, _ = step_jit(jax.random.PRNGKey(1), st, a, _params(**penalty))
    np.testing.assert_array_equal(st0.plant.rho, st1.plant.rho)
    return st, st0, r0, r1


def test_h_rate_cost_in_the_reward():
    """h_rate_weight w subtracts w * (dx / 5 m) sum_i ((h_i - h_prev_i)/h_bar)^2 of the time gap
    commanded at this step; zero gains at the start command h_bar, so they cost nothing."""
    w = 0.3
    st, st0, r0, r1 = _step_with_and_without(h_rate_weight=w)
    h_new = np.asarray(st0.plant.h_prev, np.float64)  # the gap commanded at this step
    expected = np.sum(((h_new - np.asarray(st.plant.h_prev)) / float(TP.h_bar)) ** 2) * float(TP.dx) / 5.0
    assert expected > 0.0
    cost = learn_env.h_rate_cost(st.plant.h_prev, st0.plant.h_prev, TP.h_bar, TP.dx)
    np.testing.assert_allclose(float(cost), expected, rtol=1e-5)
    np.testing.assert_allclose(float(r1), float(r0) - w * expected, rtol=1e-5)
    _, _, r_zero, _, _ = step_jit(jax.random.PRNGKey(1), st, jnp.zeros(3), _params(h_rate_weight=w))
    _, _, r_zero_ref, _, _ = step_jit(jax.random.PRNGKey(1), st, jnp.zeros(3), _params())
    np.testing.assert_allclose(float(r_zero), float(r_zero_ref), rtol=1e-6)
    with pytest.raises(ValueError, match="h_rate_weight"):
        _params(h_rate_weight=-1.0)


def test_backward_wave_cost():
    """0 at or above the speed threshold, linear below it down to 1 at 5 m/s below (the open loop,
    s = lambda2 = -3.6 m/s, costs 0.92 at a 1 m/s threshold), 1 across the singular surface; in the
    reward it is charged on the applied gains."""
    from jaxtraffic.control.gain_law import lyapunov_equivalent_gains
    from jaxtraffic.model.linear import gain_law_wave_speed, linearize

    lm = linearize(TP)
    cost = lambda g, smin=1.0: float(learn_env.backward_wave_cost(jnp.asarray(g, jnp.float32), lm, smin))  # noqa: E731
    lyap = np.asarray(lyapunov_equivalent_gains(1.0, TP))  # s = v_bar ~ 3.1 m/s
    assert cost(lyap) == 0.0
    assert cost(np.zeros(3)) == pytest.approx((1.0 - float(lm.lam2)) / 5.0, rel=1e-5)  # open loop, ramp 5 m/s
    assert cost(np.zeros(3), smin=3.0) == 1.0
    s_lyap = float(gain_law_wave_speed(jnp.asarray(lyap), lm))
    assert cost(lyap, smin=s_lyap + 2.5) == pytest.approx(0.5, abs=1e-5)  # 2.5 m/s short of the threshold, scale 5
    assert cost([0.0, 1.3 * 1.283333, 0.0]) == 1.0  # denominator < 0: s flipped through infinity
    w = 0.4
    st, st0, r0, r1 = _step_with_and_without(wave_weight=w, wave_speed_min=1.0)
    gains = gp.filter_gains(st.gains, learn_env.action_to_gains(jnp.array([0.2, 0.1, -0.3]), _params()), 1.0)
    np.testing.assert_allclose(float(r1), float(r0) - w * cost(gains), rtol=1e-5, atol=1e-7)
    assert cost(gains) > 0.0
    with pytest.raises(ValueError, match="wave_weight"):
        _params(wave_weight=-1.0)


def test_sensor_noise_one_draw_per_step_feeds_the_observation_and_the_law():
    """``EnvConfig.train_sensor_noise``: the observation is the policy's features of the held measurement (the
    factors in ``EnvState.noise``), the next step's law acts on that same measurement, a fresh one is drawn every
    step at the episode's level, and a level of 0 reproduces the noise-free environment (the other draws unchanged)."""
    from jaxtraffic.control.noise import held_noise, measured
    from jaxtraffic.sim.plant import closed_loop_step, plant_alpha

    quiet, zero, noisy = _params(), _params(sensor_noise=True), _params(sensor_noise=True, noise_min=0.05,
                                                                          noise_max=0.1)
    a = jnp.array([0.4, -0.3, 0.2])
    (o0, s0), (oz, sz), (on, sn) = (reset_jit(jax.random.PRNGKey(3), p) for p in (quiet, zero, noisy))
    assert s0.noise is None and sz.noise.shape == (2, N) and 0.05 <= float(sn.noise_level) <= 0.1
    np.testing.assert_array_equal(sz.noise, 1.0)
    np.testing.assert_allclose(oz, o0, rtol=0, atol=1e-6)
    eq = equilibrium(TP)
    seen = gp.policy_features(measured(sn.plant.observation(TP), sn.noise), sn.gains, TP, noisy.gain_max, eq)
    np.testing.assert_allclose(on, seen, rtol=0, atol=1e-6)
    assert not np.allclose(on, o0, atol=1e-3)  # the noise moves the observation
    for st, p in ((s0, quiet), (sz, zero)):  # level 0: the noise-free step
        k = jax.random.PRNGKey(9)
        out = step_jit(k, st, a, p)
        if p is quiet:
            ref = out
    np.testing.assert_allclose(out[0], ref[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(out[1].plant.rho, ref[1].plant.rho, rtol=1e-6)
    k = jax.random.PRNGKey(9)
    _, s1, _, _, info = step_jit(k, sn, a, noisy)
    ctrl = gp.gain_target_controller(learn_env.action_to_gains(a, noisy), noisy.gain_filter, eq, noisy.filter_nodes)
    k_plant = jax.random.split(k)[0]
    alpha = plant_alpha(sn.plant_params, k_plant)
    held = closed_loop_step(sn.plant, sn.gains, held_noise(ctrl, sn.noise), sn.plant_params, TP, alpha, k_plant, eq)
    raw = closed_loop_step(sn.plant, sn.gains, ctrl, sn.plant_params, TP, alpha, k_plant, eq)
    for x, y in zip(jax.tree.leaves(s1.plant), jax.tree.leaves(held[0]), strict=True):  # the law saw the held
        np.testing.assert_allclose(x, y, rtol=1e-6)                                      # measurement
    np.testing.assert_allclose(s1.gains, held[1], rtol=1e-6)
    assert not np.allclose(held[2], raw[2], rtol=1e-4)
    assert float(s1.noise_level) == float(sn.noise_level) and not np.allclose(s1.noise, sn.noise)
    e = (np.asarray(s1.noise) - 1.0) / float(sn.noise_level)  # the fresh draw: standard normal
    assert abs(e.mean()) < 0.5 and 0.5 < e.std() < 1.6
