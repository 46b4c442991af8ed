"""jaxtraffic.ecosystem.gymnax_env on a tiny grid: a real gymnax Environment, gymnax's wrappers under
vmap + scan, and examples/gymnax_ppo.py (a third-party-style PPO) for a few updates. Skipped
without gymnax (``pip install -e ".[gymnax]"``)."""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from extras import need

need("gymnax")
from gymnax.environments import environment, spaces  # noqa: E402
from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper  # noqa: E402
from tiny_runs import REPO, xla_env  # noqa: E402

from jaxtraffic.control.gain_policy import feature_size  # noqa: E402
from jaxtraffic.ecosystem.gymnax_env import GainGymnaxEnv  # noqa: E402
from jaxtraffic.learn.env import EnvParams  # noqa: E402

N = 21
CONFIG = {"n_points": N, "delay": 0.5, "max_delay_steps": 20, "horizon_s": 1.0, "delay_spread": 0.0}
OBS = feature_size(N, EnvParams().obs_segments)  # the training default: the pooled observation


def test_is_a_gymnax_environment():
    env = GainGymnaxEnv(gain_filter=1.0, **CONFIG)
    p = env.default_params
    assert isinstance(env, environment.Environment)
    assert env.name == "jaxtraffic/Gain-v0" and env.num_actions == 3 and int(p.horizon) == 10
    obs_space, act_space = env.observation_space(p), env.action_space(p)
    assert isinstance(obs_space, spaces.Box) and obs_space.shape == (OBS,)
    assert isinstance(act_space, spaces.Box) and act_space.shape == (3,)
    assert np.all(np.asarray(act_space.low) == -1.0) and np.all(np.asarray(act_space.high) == 1.0)
    obs, st = env.reset(jax.random.PRNGKey(0), p)
    assert obs.shape == obs_space.shape and bool(obs_space.contains(obs))
    out = env.step(jax.random.PRNGKey(1), st, jnp.array([0.5, -1.0, 2.0]), p)
    assert len(out) == 6  # gymnax 1.0: obs, state, reward, terminated, truncated, info
    obs2, st2, r, term, trunc, info = out
    assert r.shape == () and not bool(term) and not bool(trunc)
    np.testing.assert_allclose(info["final_observation"], obs2, atol=1e-6)  # no reset: the same observation
    # normalised gains (clipped to the box) times gain_max; gain_filter 1: applied directly
    np.testing.assert_allclose(info["gains"], p.gain_max * np.array([0.5, -1.0, 1.0]), rtol=1e-5)


def test_wrappers_under_vmap_and_scan():
    env = GainGymnaxEnv(**CONFIG)
    wenv = LogWrapper(FlattenObservationWrapper(env))
    p, n, T = env.default_params, 4, 25
    obs, st = jax.vmap(wenv.reset, (0, None))(jax.random.split(jax.random.PRNGKey(0), n), p)

    def body(carry, k):
        obs, st = carry
        ks = jax.random.split(k, n)
        a = jax.vmap(env.action_space(p).sample)(ks)
        obs2, st, r, term, trunc, info = jax.vmap(wenv.step, (0, 0, 0, None))(ks, st, a, p)
        return (obs2, st), {"obs": obs2, "r": r, "trunc": trunc, "term": term, "final": info["final_observation"],
                            "ret": info["returned_episode_returns"], "ended": info["returned_episode"]}

    _, out = jax.jit(lambda c: jax.lax.scan(body, c, jax.random.split(jax.random.PRNGKey(1), T)))((obs, st))
    out = jax.tree.map(np.asarray, out)
    assert out["obs"].shape == (T, n, OBS) and np.isfinite(out["r"]).all()
    ends = out["trunc"] | out["term"]
    assert ends[9].all() and ends[19].all() and ends.sum() == 2 * n  # horizon 10 steps, every env
    np.testing.assert_array_equal(ends, out["ended"])
    # LogWrapper's episode return = the sum of the episode's rewards
    np.testing.assert_allclose(out["ret"][9], out["r"][:10].sum(0), rtol=1e-5)
    # at an episode end, the returned observation is the new episode's (no gains yet), the final one is not
    np.testing.assert_array_equal(out["obs"][9][:, -3:], 0.0)
    assert np.abs(out["final"][9][:, -3:]).max() > 0
    np.testing.assert_allclose(out["final"][8], out["obs"][8], atol=1e-6)


@pytest.mark.slow  # end to end (seconds to tens of seconds): CI's slow tier
def test_example_purejaxrl_style_ppo_trains():
    """The example as a user runs it (a subprocess, with the test XLA flags: cheaper compilation)."""
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "gymnax_ppo.py"), "--n-points", str(N),
                           "--horizon-s", "1", "--num-envs", "8", "--num-steps", "16", "--num-updates", "3",
                           "--update-epochs", "2", "--num-minibatches", "2", "--num-seeds", "2"],
                          cwd=REPO, capture_output=True, text=True, timeout=1200,
                          env=xla_env(PYTHONPATH=os.pathsep.join(filter(None, [str(REPO),
                                                                               os.environ.get("PYTHONPATH")]))))
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "2 seed(s) x 3 updates x 8 envs x 16 steps" in out and "env steps/s" in out, out
    last = [x for x in out.splitlines() if "last update" in x][0]
    returns = [float(v) for v in last.split("[")[1].split("]")[0].split()]
    assert len(returns) == 2 and np.isfinite(returns).all() and all(r < 0 for r in returns), last



def test_gymnax_make_finds_the_registered_id():
    import gymnax

    env, params = gymnax.make("jaxtraffic/Gain-v0", **CONFIG)  # registered by importing gymnax_env (above)
    assert isinstance(env, GainGymnaxEnv) and "jaxtraffic/Gain-v0" in gymnax.registered_envs
    assert int(params.horizon) == 10 and env.observation_space(params).shape == (OBS,)


def _python(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**xla_env(), "PYTHONPATH": str(REPO)}, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_import_jaxtraffic_registers_with_an_imported_gymnax():
    """gymnax imported first, then jaxtraffic (no gymnax module of jaxtraffic imported by hand): ``make``
    works; ``import jaxtraffic`` alone does not import gymnax (~1.2 s)."""
    made = _python("import gymnax, jaxtraffic; env, p = gymnax.make('jaxtraffic/Gain-v0', n_points=21); "
                   "print(type(env).__name__, int(p.horizon))")
    assert made == "GainGymnaxEnv 1000"  # the default 100 s horizon, dt 0.1 s
    assert _python("import sys, jaxtraffic; print('gymnax' in sys.modules)") == "False"
