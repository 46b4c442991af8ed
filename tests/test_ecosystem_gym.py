"""jaxtraffic.ecosystem.gym_env / sb3 on a tiny grid: gymnasium's check_env on the single env, the
batched vector env (same-step autoreset, final observations, seeding), the id registered by plain
``import jaxtraffic`` (and the module-prefixed id), the SB3
VecEnv adapter and examples/sb3_ppo.py. Skipped without gymnasium (``pip install -e ".[gym]"``);
the SB3 tests also need stable-baselines3 (``[sb3]``)."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env  # noqa: E402

from jaxtraffic.control.gain_policy import feature_size  # noqa: E402
from jaxtraffic.ecosystem import ENV_ID  # noqa: E402
from jaxtraffic.ecosystem.gym_env import GainEnv, GainVectorEnv  # noqa: E402
from jaxtraffic.learn.env import EnvParams  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
N = 21
CONFIG = {"n_points": N, "delay": 0.5, "max_delay_steps": 20, "horizon_s": 1.0, "delay_spread": 0.0}
OBS = feature_size(N, EnvParams().obs_segments)  # the training default: the pooled observation


def test_check_env_and_make():
    env = gym.make(ENV_ID, **CONFIG)
    assert isinstance(env.unwrapped, GainEnv)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    assert env.observation_space.shape == (OBS,) and env.observation_space.dtype == np.float32
    obs, info = env.reset(seed=3)
    assert obs.shape == (OBS,) and obs.dtype == np.float32
    for t in range(10):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        assert isinstance(r, float) and not term and trunc == (t == 9)
    assert np.abs(obs[-3:]).max() > 0  # the episode's last observation (gains applied), not a reset one
    other = gym.make("jaxtraffic:" + ENV_ID, **CONFIG)  # the module-prefixed id
    np.testing.assert_array_equal(other.reset(seed=3)[0], env.reset(seed=3)[0])


# a fresh interpreter: gymnasium first, then plain ``import jaxtraffic`` registers the id (lazily:
# the environment module is imported by make); or the module-prefixed id with no import at all
FRESH = r"""
import json, sys
import gymnasium as gym
cfg = json.loads(sys.argv[1])
out = {"before": "jaxtraffic/Gain-v0" in gym.registry}
if sys.argv[2] == "import":
    import jaxtraffic
    out["registered"] = "jaxtraffic/Gain-v0" in gym.registry
    out["lazy"] = "jaxtraffic.ecosystem.gym_env" not in sys.modules and "jaxtraffic.learn.env" not in sys.modules
    env = gym.make("jaxtraffic/Gain-v0", **cfg)
else:
    env = gym.make("jaxtraffic:jaxtraffic/Gain-v0", **cfg)
out["cls"] = type(env.unwrapped).__module__ + "." + type(env.unwrapped).__name__
print("RESULT " + json.dumps(out))
"""


@pytest.mark.parametrize("how", ["import", "prefix"])
def test_make_after_plain_import_or_with_module_prefix(how):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
           "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", FRESH, json.dumps(CONFIG), how], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(next(x for x in out.stdout.splitlines() if x.startswith("RESULT "))[7:])
    assert res.pop("before") is False and res.pop("cls") == "jaxtraffic.ecosystem.gym_env.GainEnv"
    assert all(res.values()), res


def test_vector_env_same_step_autoreset_and_seeding():
    venv = gym.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", **CONFIG)
    assert isinstance(venv, GainVectorEnv) and venv.num_envs == 4
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert venv.single_action_space == gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (4, OBS) and obs.dtype == np.float32 and venv.observation_space.contains(obs)
    np.testing.assert_array_equal(venv.reset(seed=0)[0], obs)
    venv.action_space.seed(0)
    acts = [venv.action_space.sample() for _ in range(12)]

    def run():
        venv.reset(seed=0)
        return [venv.step(a) for a in acts]

    first, second = run(), run()
    for a, b in zip(first, second, strict=True):  # same seed, same actions: same trajectory
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    for t, (obs, r, term, trunc, info) in enumerate(first):
        assert r.shape == (4,) and r.dtype == np.float32 and np.isfinite(r).all()
        assert obs.shape == (4, OBS) and not term.any() and trunc.all() == (t == 9) and trunc.any() == (t == 9)
        assert info["gains"].shape == (4, 3)
        if t == 9:
            assert info["_final_obs"].all() and info["final_obs"].dtype == object
            final = np.stack(info["final_obs"])
            assert final.shape == (4, OBS) and np.abs(final[:, -3:]).max() > 0
            np.testing.assert_array_equal(obs[:, -3:], 0.0)  # reset in the same step: no gains applied yet
        else:
            assert "final_obs" not in info
    venv.close()
    # with randomised initial amplitudes the seed matters
    rand = GainVectorEnv(num_envs=4, **{**CONFIG, "amp_range": (0.005, 0.015)})
    a, b, c = (rand.reset(seed=s)[0] for s in (0, 0, 1))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_vector_env_step_matches_single_env_spaces():
    venv = GainVectorEnv(num_envs=2, **CONFIG)
    env = GainEnv(**CONFIG)
    assert venv.single_observation_space == env.observation_space
    with pytest.raises(gym.error.ResetNeeded):
        venv.step(np.zeros((2, 3), np.float32))


def test_sb3_vec_env_adapter_and_example():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    from jaxtraffic.ecosystem.sb3 import SB3VecEnv

    sb3_check_env(GainEnv(**CONFIG))
    venv = SB3VecEnv(num_envs=3, **CONFIG)
    venv.seed(5)
    obs = venv.reset()
    assert obs.shape == (3, OBS)
    for t in range(10):
        obs, rew, dones, infos = venv.step(np.zeros((3, 3), np.float32))
        assert dones.all() == (t == 9) and len(infos) == 3
    assert all(i["TimeLimit.truncated"] and i["terminal_observation"].shape == (OBS,) for i in infos)
    assert venv.get_attr("render_mode") == [None] * 3 and venv.env_is_wrapped(object) == [False] * 3

    spec = importlib.util.spec_from_file_location("sb3_ppo", REPO / "examples" / "sb3_ppo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--n-points", str(N), "--horizon-s", "1", "--num-envs", "8", "--n-steps", "16",
                    "--total-timesteps", "256"])
    assert res["num_timesteps"] >= 256 and len(res["returns"]) > 0 and np.isfinite(res["returns"]).all()
