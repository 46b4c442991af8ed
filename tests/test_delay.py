"""Input delay (docs/model.md section 4): ring buffer, exact d-step delay, h_bar before t = D."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL, bump_state

from jaxtraffic import Controller, TrafficParams, equilibrium_state, simulate, simulate_batch, stack_params
from jaxtraffic.model import delay as db
from jaxtraffic.sim import Record
from jaxtraffic.sim.plant import initial_state, plant_step


def test_buffer_starts_filled_with_h0():
    h0 = jnp.full((5,), 1.5)
    buf = db.init_buffer(h0, 7)
    assert buf.size == 8 and buf.data.shape == (8, 5)
    for k in range(8):
        np.testing.assert_array_equal(db.read(buf, k), h0)


def test_buffer_read_k_steps_ago_with_wraparound():
    cap = 4
    buf = db.init_buffer(jnp.zeros(3), cap)
    read = jax.jit(db.read)  # k traced
    for m in range(1, 12):  # wraps around the ring several times
        buf = db.push(buf, jnp.full((3,), float(m)))
        for k in range(cap + 1):
            expected = float(m - k) if m - k >= 1 else 0.0  # 0: the initial fill
            np.testing.assert_array_equal(read(buf, k), np.full(3, expected), err_msg=f"m={m} k={k}")


def test_buffer_push_keeps_dtype_and_shape():
    buf = db.init_buffer(jnp.zeros(4, jnp.float32), 3)
    with pytest.raises(AssertionError):
        db.push(buf, jnp.zeros(5))
    buf = db.push(buf, jnp.ones(4, jnp.float32))
    assert buf.data.dtype == jnp.float32


@jax.jit
def _pulse_scan(p: TrafficParams, n_pulse, pulse_amp):
    """Plant states after each of ``N_PULSE_STEPS`` plant steps from equilibrium, sending h_bar
    except h_bar + ``pulse_amp`` at step ``n_pulse``."""
    rho, v = equilibrium_state(p)
    key = jax.random.PRNGKey(0)

    def body(state, n):
        h = jnp.where(n == n_pulse, p.h_bar + pulse_amp, p.h_bar) * jnp.ones_like(state.rho)
        new = plant_step(state, h, p, jax.random.fold_in(key, n))
        return new, (new.rho, new.v)

    _, (rs, vs) = jax.lax.scan(body, initial_state(p, rho, v), jnp.arange(N_PULSE_STEPS))
    return rs, vs  # rs[n] = state after step n (at t_{n+1})


N_PULSE_STEPS = 120


@pytest.mark.parametrize("d", [0, 1, 3, 10, 100])
def test_pulse_reaches_plant_exactly_d_steps_later(d):
    p = TrafficParams(**SMALL, delay=d * SMALL["dt"])
    assert int(p.delay_steps) == d
    n_pulse = 5
    r1, v1 = _pulse_scan(p, n_pulse, 1.5)
    r0, v0 = _pulse_scan(p, n_pulse, 0.0)
    # steps 0 .. n_pulse + d - 1 apply h_bar in both runs: identical states
    k = n_pulse + d
    np.testing.assert_array_equal(r1[:k], r0[:k])
    np.testing.assert_array_equal(v1[:k], v0[:k])
    # step n_pulse + d applies the pulse: the speed changes at every node (source term)
    assert np.all(np.asarray(v1[k]) != np.asarray(v0[k]))


def test_plant_applies_delayed_input_like_a_direct_solver_step():
    """With delay d the plant step n uses exactly the field sent at step n - d."""
    from jaxtraffic.model.solver import arz_step

    d = 4
    p = TrafficParams(**SMALL, delay=d * SMALL["dt"])
    rho, v = bump_state(p)
    sent = [jnp.full_like(rho, 0.5 + 0.1 * n) for n in range(12)]  # distinct fields
    state = initial_state(p, rho, v)
    r_ref, v_ref = rho, v
    for n, h in enumerate(sent):
        state = jax.jit(plant_step)(state, h, p, jax.random.PRNGKey(n))
        h_app = sent[n - d] if n >= d else jnp.full_like(rho, p.h_bar)
        r_ref, v_ref, _, _ = jax.jit(arz_step)(r_ref, v_ref, h_app, p)
        np.testing.assert_allclose(state.rho, r_ref, rtol=1e-6, err_msg=f"step {n}")
        np.testing.assert_allclose(state.v, v_ref, rtol=1e-6, err_msg=f"step {n}")
        np.testing.assert_array_equal(state.h_prev, h)


# A controller that sends h_bar + amp during steps n0 .. n1 and h_bar otherwise (traced settings).
def _window_act(settings, cstate, obs, nominal, key):
    step = jnp.round(obs.t / nominal.dt).astype(jnp.int32)
    on = (step >= settings["n0"]) & (step <= settings["n1"])
    return jnp.full_like(obs.rho, nominal.h_bar + jnp.where(on, settings["amp"], 0.0)), cstate


def window_controller(n0, n1, amp) -> Controller:
    settings = {"n0": jnp.asarray(n0, jnp.int32), "n1": jnp.asarray(n1, jnp.int32),
                "amp": jnp.asarray(amp, jnp.float32)}
    return Controller(settings=settings, act_fn=_window_act, name="window")


def test_rollout_pulse_delays_in_one_batch():
    """One compiled batched rollout over several delays: the pulse sent at step n shows in the
    state only after step n + d, for each environment's own d."""
    dt = SMALL["dt"]
    delays = [0, 2, 7, 40]
    n_pulse, n_steps = 3, 50
    p = stack_params(delay=[d * dt for d in delays] * 2, **SMALL)
    amps = [1.0] * len(delays) + [0.0] * len(delays)
    pulse_at = jnp.full((2 * len(delays),), n_pulse)
    ctrl = window_controller(pulse_at, pulse_at, jnp.asarray(amps))
    rho, v = equilibrium_state(TrafficParams(**SMALL))
    res = simulate_batch(p, ctrl, n_steps=n_steps, rho0=jnp.stack([rho] * 8), v0=jnp.stack([v] * 8),
                         record=Record(every=1), batch_controller=True)
    vt = np.asarray(res.trajectory.v)  # (8, n_steps, n) state at t_0 .. t_{n_steps-1}
    ht = np.asarray(res.trajectory.h)  # sent fields
    for i, d in enumerate(delays):
        with_pulse, without = vt[i], vt[i + len(delays)]
        assert np.all(ht[i, n_pulse] == 2.5) and np.all(ht[i + len(delays), n_pulse] == 1.5)
        k = n_pulse + d  # the step that applies the pulse; its result is the state at t_{k+1}
        np.testing.assert_array_equal(with_pulse[: k + 1], without[: k + 1], err_msg=f"d={d}")
        assert np.all(with_pulse[k + 1] != without[k + 1]), f"d={d}"


def test_plant_receives_h_bar_before_t_equals_D():
    """From a non-equilibrium state, sending h = 3 s from t = 0 leaves the first d steps identical
    to the open loop (h_bar), and the step d differs."""
    d = 6
    p = TrafficParams(**SMALL, delay=d * SMALL["dt"])
    rho, v = bump_state(p)
    res_ol = simulate(p, window_controller(0, 10**6, 0.0), n_steps=20, rho0=rho, v0=v, record=Record(every=1))
    res_hi = simulate(p, window_controller(0, 10**6, 1.5), n_steps=20, rho0=rho, v0=v, record=Record(every=1))
    t_ol, t_hi = res_ol.trajectory, res_hi.trajectory
    assert np.all(np.asarray(t_hi.h) == 3.0) and np.all(np.asarray(t_ol.h) == 1.5)
    np.testing.assert_array_equal(t_hi.v[: d + 1], t_ol.v[: d + 1])
    np.testing.assert_array_equal(t_hi.rho[: d + 1], t_ol.rho[: d + 1])
    assert np.all(np.asarray(t_hi.v[d + 1]) != np.asarray(t_ol.v[d + 1]))
