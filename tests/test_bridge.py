"""Policies across ecosystems: a function of the environment's observation as a ``Controller``
(``control.gain_policy.function_controller``, ``ecosystem.policy_as_controller``). A trained run's policy as
a plain ``predict(obs)``: ``test_trained_run_export.py``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL

from jaxtraffic import simulate, simulate_batch, stack_params
from jaxtraffic.control.gain_policy import feature_size, function_controller, gain_target_controller

A = np.array([0.25, -0.5, -0.75], np.float32)
GAIN_MAX = 2.0


def _constant(obs):
    return np.broadcast_to(A, obs.shape[:-1] + (3,))


@pytest.mark.parametrize("host", [True, False])
def test_a_constant_function_is_the_three_gain_law_at_those_gains(small, host):
    """A function returning fixed normalised gains a acts as the three-gain law at gain_max * a, whether it
    runs on the host (``pure_callback``) or is traced (a JAX function)."""
    fn = _constant if host else (lambda obs: jnp.broadcast_to(jnp.asarray(A), obs.shape[:-1] + (3,)))
    ctrl = function_controller(fn, GAIN_MAX, host=host)
    ref = gain_target_controller(jnp.asarray(GAIN_MAX * A))
    got, want = (simulate(small, c, n_steps=40).metrics for c in (ctrl, ref))
    for k in ("J_comfort", "final_rho_L2", "final_v_L2"):
        np.testing.assert_allclose(float(got[k]), float(want[k]), rtol=1e-5, err_msg=k)


def test_the_function_sees_the_environments_observation_and_runs_batched(small):
    seen = []

    def record(obs):
        seen.append(obs.shape)
        return _constant(obs)

    envs = stack_params(**SMALL, delay=[0.0, 1.0, 2.0])
    for batched in (False, True):
        seen.clear()
        ctrl = function_controller(record, GAIN_MAX, obs_segments=4, batched=batched)
        res = simulate_batch(envs, ctrl, n_steps=3, nominal=small, keys=jax.random.split(jax.random.PRNGKey(0), 3))
        assert np.isfinite(np.asarray(res.metrics["J_comfort"])).all()
        size = feature_size(small.n_points, 4)
        assert set(seen) == ({(3, size)} if batched else {(size,)})  # one call per step, or one per environment
