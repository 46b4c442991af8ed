"""The environment's automatic reset only where an episode ended (issue 39): ``learn.env.auto_reset``
gives what a select of a fresh episode everywhere gives, unbatched, under ``vmap`` and nested ``vmap``
(seeds x environments), and with batched parameters (its fallback)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic.learn import env as E
from jaxtraffic.model.params import TrafficParams, equilibrium

EP = E.make_env_params(TrafficParams(n_points=21, delay=0.5, max_delay_steps=20), filter_sigma=0.0, horizon=5,
                       amp_min=0.005, amp_max=0.02, delay_min=0.2, delay_max=0.5, alpha_min=0.1, alpha_max=0.3)
EQ = equilibrium(EP.traffic)
B = 4


def _stepped_batch(seed: int = 0):
    """A batch of B environments a few steps into their episodes, their observations and keys."""
    keys = jax.random.split(jax.random.PRNGKey(seed), B)
    _, state = jax.vmap(E.reset_env, (0, None))(keys, EP)
    for i in range(3):
        _, state, _, _, _ = jax.vmap(E.step_env, (0, 0, 0, None))(
            jax.random.split(jax.random.PRNGKey(10 + i), B), state, jnp.full((B, 3), 0.3), EP)
    obs = jax.vmap(E.observe, (0, None))(state, EP)
    return state, obs, jax.random.split(jax.random.PRNGKey(seed + 100), B)


def _assert_close(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=2e-6, atol=1e-7)
        else:
            np.testing.assert_array_equal(x, y)


def _select(done, keys, state, obs):
    return jax.vmap(E._select_reset, (0, 0, 0, 0, None, None))(done, keys, state, obs, EP, EQ)


@pytest.mark.parametrize("done", [(False, False, False, False), (True, False, True, False), (True,) * 4])
def test_auto_reset_under_vmap_is_the_select(done):
    state, obs, keys = _stepped_batch()
    done = jnp.asarray(done)
    got = jax.jit(jax.vmap(E.auto_reset, (0, 0, 0, 0, None, None)))(done, keys, state, obs, EP, EQ)
    _assert_close(got, _select(done, keys, state, obs))
    # environments that did not finish are untouched, bit for bit (buffer storage included)
    keep = ~np.asarray(done)
    for x, y in zip(jax.tree.leaves((obs, state)), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(np.asarray(x)[keep], np.asarray(y)[keep])
    # finished ones start a new episode
    np.testing.assert_array_equal(np.asarray(got[1].t)[~keep], 0)


def test_auto_reset_nested_vmap_and_single_environment():
    state, obs, keys = _stepped_batch()
    done = jnp.asarray([False, True, False, True])
    expect = _select(done, keys, state, obs)
    seeds = jax.tree.map(lambda x: jnp.stack([x, x]), (done, keys, state, obs))  # 2 seeds x B environments
    nested = jax.jit(jax.vmap(jax.vmap(E.auto_reset, (0, 0, 0, 0, None, None)), (0, 0, 0, 0, None, None)))
    got = nested(*seeds, EP, EQ)
    _assert_close(jax.tree.map(lambda x: x[1], got), expect)
    one = jax.tree.map(lambda x: x[1], (done, keys, state, obs))
    single = jax.jit(E.auto_reset)(*one, EP, EQ)
    _assert_close(single, jax.tree.map(lambda x: x[1], expect))


def test_auto_reset_with_batched_parameters_falls_back_to_the_select():
    state, obs, keys = _stepped_batch()
    done = jnp.asarray([True, False, False, True])
    eps = jax.tree.map(lambda x: jnp.stack([jnp.asarray(x)] * B), EP)
    eps = eps.replace(amp_max=jnp.linspace(0.01, 0.03, B))
    eqs = jax.vmap(lambda p: equilibrium(p.traffic))(eps)
    got = jax.jit(jax.vmap(E.auto_reset))(done, keys, state, obs, eps, eqs)
    expect = jax.vmap(E._select_reset)(done, keys, state, obs, eps, eqs)
    _assert_close(got, expect)


def test_step_env_resets_at_the_horizon_and_runs_on():
    """Episodes of ``horizon`` steps end together; the step after starts new ones (t = 0) and goes on."""
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    _, state = jax.vmap(E.reset_env, (0, None))(keys, EP)
    step = jax.jit(jax.vmap(E.step_env, (0, 0, 0, None)))
    for i in range(EP.horizon):
        obs, state, r, done, info = step(jax.random.split(jax.random.PRNGKey(i), B), state, jnp.zeros((B, 3)), EP)
    assert bool(np.all(np.asarray(done))) and bool(np.all(np.asarray(state.t) == 0))
    assert np.all(np.isfinite(np.asarray(obs)))
    assert not np.array_equal(np.asarray(obs), np.asarray(info["terminal_obs"]))


def test_the_reset_is_chosen_by_backend_unless_set(monkeypatch):
    """``RESET_ONLY_WHERE_DONE`` None (default): the cond-guarded reset on a CPU, the select on an accelerator
    (a ``lax.cond`` there waits for the host every step); True/False force either; the step's program follows."""
    assert E.RESET_ONLY_WHERE_DONE is None
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert not E.reset_only_where_done()
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    assert E.reset_only_where_done()
    monkeypatch.setattr(E, "RESET_ONLY_WHERE_DONE", False)
    assert not E.reset_only_where_done()

    def step_jaxpr() -> str:
        state = jax.vmap(E.reset_env, (0, None))(jax.random.split(jax.random.PRNGKey(0), B), EP)[1]
        return str(jax.make_jaxpr(lambda k, s: jax.vmap(E.step_env, (0, 0, 0, None))(k, s, jnp.zeros((B, 3)), EP))(
            jax.random.split(jax.random.PRNGKey(1), B), state))

    assert " cond[" not in step_jaxpr()
    monkeypatch.setattr(E, "RESET_ONLY_WHERE_DONE", None)
    assert " cond[" in step_jaxpr()  # (a CPU: the reset only where done)


def test_sensor_noise_state_crosses_episode_boundaries_alike_under_both_resets(monkeypatch):
    """With sensor noise from a train-split pool: every episode's level is its pool scenario's, a reset draws a
    fresh level and measurement, and the reset where done gives what the select gives (horizon 2, 5 steps)."""
    from jaxtraffic.compare.scenarios import EpisodePool

    tp = TrafficParams(n_points=21, delay=0.5)  # (a buffer for the split's delays, up to 8 s)
    pool = EpisodePool.train_split(6, tp, (0.02, 0.08))
    ep = E.make_env_params(tp, filter_sigma=0.0, horizon=2, pool=pool, sensor_noise=True)
    levels = np.asarray(pool.noise)
    runs = {}
    for where_done in (True, False):
        monkeypatch.setattr(E, "RESET_ONLY_WHERE_DONE", where_done)
        step = jax.jit(jax.vmap(E.step_env, (0, 0, 0, None)))  # (a new jit: the flag is read when traced)
        _, state = jax.vmap(E.reset_env, (0, None))(jax.random.split(jax.random.PRNGKey(1), B), ep)
        seen = [state]
        for i in range(5):
            _, state, _, _, _ = step(jax.random.split(jax.random.PRNGKey(20 + i), B), state, jnp.full((B, 3), 0.3), ep)
            seen.append(state)
        runs[where_done] = seen
    _assert_close(runs[True], runs[False])
    seen = runs[True]
    for st in seen:
        assert np.all(np.min(np.abs(np.asarray(st.noise_level)[:, None] - levels[None]), axis=1) < 1e-7)
    assert all(np.asarray(st.t).max() <= 1 for st in seen)
    # the second step ends every episode (horizon 2): the state after it is a fresh episode's, noise included
    fresh = jax.vmap(E.reset_env, (0, None))(jax.vmap(lambda k: jax.random.split(k)[1])(
        jax.random.split(jax.random.PRNGKey(21), B)), ep)[1]
    _assert_close((seen[2].noise_level, seen[2].noise), (fresh.noise_level, fresh.noise))
    assert not np.allclose(seen[2].noise_level, seen[1].noise_level)
