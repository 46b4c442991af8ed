"""A policy as a controller (jaxtraffic/control/gain_policy.py) against the training environment, tiny grid."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic.control.gain_policy import equilibrium_gains, policy_controller
from jaxtraffic.control.networks import ActorCritic
from jaxtraffic.learn import env as learn_env
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.sim import Record, equilibrium_state, simulate

TP = TrafficParams(n_points=21, delay=0.5)
HIDDEN = (16,)
STEPS = 40


def _random_policy(ep: learn_env.EnvParams, seed: int = 0, scale: float = 0.5):
    """Network parameters perturbed away from the (near-zero-output) initialisation, and
    observation statistics that are not the identity, so every part of the input path matters."""
    net = ActorCritic(hidden=HIDDEN, init_sigma=0.3)
    k_init, k_noise, k_mean, k_var = jax.random.split(jax.random.PRNGKey(seed), 4)
    params = net.init(k_init, jnp.zeros((learn_env.obs_size(ep),)))
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(k_noise, len(leaves))
    noisy = [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys, strict=True)]
    params = jax.tree.unflatten(tree, noisy)
    mean = 0.01 * jax.random.normal(k_mean, (learn_env.obs_size(ep),))
    var = jax.random.uniform(k_var, (learn_env.obs_size(ep),), minval=0.005, maxval=0.02)
    return net, params, mean, var


def _env(**kw) -> learn_env.EnvParams:
    """Full observation and one gain bound unless ``kw`` says otherwise."""
    return learn_env.make_env_params(TP, **{"gain_max": 2.0, "obs_segments": 0, **kw})


@pytest.mark.parametrize("gain_filter,segments,gain_max", [(1.0, 0, 2.0), (0.3, 0, 2.0), (0.3, 4, (0.9, 2.0, 2.5))])
def test_policy_controller_replays_the_environment(gain_filter, segments, gain_max):
    """``simulate`` with the policy controller applies, step for step, the gains the environment
    applies for the policy's deterministic action (same observation, same filter, same law), so
    the evaluation of a trained policy is the rollout it was trained on; also with a pooled
    observation and one bound per gain."""
    ep = _env(horizon=10 * STEPS, gain_max=gain_max, gain_filter=gain_filter, obs_segments=segments)
    net, params, mean, var = _random_policy(ep)
    obs, state = learn_env.reset(jax.random.PRNGKey(0), ep)
    step = jax.jit(learn_env.step)
    rho_env, gains_env = [], []
    for n in range(STEPS):
        mu, _, _ = net.apply(params, jnp.clip((obs - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0))
        obs, state, _, done, info = step(jax.random.PRNGKey(n), state, mu, ep)
        assert not bool(done)
        rho_env.append(np.asarray(state.plant.rho))
        gains_env.append(np.asarray(info["gains"]))
    gains_env = np.array(gains_env)
    assert np.ptp(gains_env, axis=0).min() > 1e-3  # the gains really vary along the rollout

    ctrl = policy_controller(params, mean, var, gain_max, hidden=HIDDEN, init_sigma=0.3, gain_filter=gain_filter,
                             obs_segments=segments, sigma_nodes=ep.filter_nodes)
    assert ep.filter_nodes > 0  # the learned law's spatial filter (the default)
    res = simulate(TP, ctrl, n_steps=STEPS, record=Record(every=1))
    np.testing.assert_allclose(res.trajectory.rho[1:], np.array(rho_env[:-1]), rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(res.final.rho, rho_env[-1], rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(res.controller_state, gains_env[-1], rtol=1e-4, atol=1e-6)


def test_gain_filter_smooths_the_time_gap():
    """A filtered policy changes the sent time gap less from step to step than the same policy
    applied directly (the filter is a low-pass on the gains)."""
    ep = _env()
    net, params, mean, var = _random_policy(ep, seed=3)

    def step_changes(k: float) -> float:
        ctrl = policy_controller(params, mean, var, 2.0, hidden=HIDDEN, init_sigma=0.3, gain_filter=k)
        h = np.asarray(simulate(TP, ctrl, n_steps=STEPS, record=Record(every=1)).trajectory.h)
        return float(np.abs(np.diff(h, axis=0)).mean())

    assert step_changes(0.1) < 0.5 * step_changes(1.0)


def test_equilibrium_gains_are_what_the_policy_settles_to():
    """At the equilibrium the filtered gains of a policy converge to a fixed point; a rollout that
    starts there applies exactly those gains after a while (the controller state)."""
    ep = _env(horizon=1000, gain_filter=0.3)
    _, params, mean, var = _random_policy(ep, seed=1, scale=0.2)
    var = var.at[-3:].set(1.0)  # a weak feedback of the gains on themselves: a stable fixed point
    ctrl = policy_controller(params, mean, var, 2.0, hidden=HIDDEN, init_sigma=0.3, gain_filter=0.3)
    g = np.asarray(equilibrium_gains(ctrl, TP))
    assert np.abs(g).max() > 1e-2  # not trivially zero
    rho, v = equilibrium_state(TP)
    res = simulate(TP, ctrl, n_steps=300, rho0=rho, v0=v)
    np.testing.assert_allclose(res.controller_state, g, rtol=1e-4, atol=1e-5)
    # a fixed point: one more step at the equilibrium leaves it unchanged
    from jaxtraffic.control import Observation
    n = TP.n_points
    obs = Observation(rho=rho, v=v, h_prev=jnp.full((n,), TP.h_bar), t=jnp.zeros(()), sent=None)
    np.testing.assert_allclose(ctrl.act(g, obs, TP, None)[1], g, rtol=1e-5, atol=1e-6)
