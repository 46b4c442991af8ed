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
from extras import need

gym = need("gymnasium")
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
    check_env(env.unwrapped)
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
    venv = gym.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", autoreset_mode="SAME_STEP",
                        **CONFIG)
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
    rand = GainVectorEnv(num_envs=4, autoreset_mode="SAME_STEP", **{**CONFIG, "amp_range": (5.0, 15.0)})
    a, b, c = (rand.reset(seed=s)[0] for s in (0, 0, 1))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def _run(venv, actions, seed=0):
    venv.reset(seed=seed)
    return [venv.step(a) for a in actions]


def test_vector_env_next_step_autoreset_is_the_default_and_matches_same_step():
    """NEXT_STEP (Gymnasium's default): the finishing step returns the episode's last observation, the
    next one resets (reward 0, not done) to the first observation SAME_STEP returned a step earlier."""
    venv = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", **CONFIG)
    assert venv.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    same = GainVectorEnv(num_envs=3, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP, **CONFIG)
    venv.action_space.seed(1)
    acts = [venv.action_space.sample() for _ in range(11)]
    nxt, sam = _run(venv, acts), _run(same, acts[:10])
    for t in range(10):  # the same episode step by step; at t = 9 NEXT_STEP returns the last observation
        np.testing.assert_array_equal(nxt[t][1], sam[t][1])
        np.testing.assert_array_equal(nxt[t][3], sam[t][3])
        expected = np.stack(sam[t][4]["final_obs"]) if t == 9 else sam[t][0]
        np.testing.assert_array_equal(nxt[t][0], expected)
        assert "final_obs" not in nxt[t][4]
    obs, r, term, trunc, info = nxt[10]  # the reset step: the first observation of the next episode
    np.testing.assert_array_equal(obs, sam[9][0])
    assert not (term.any() or trunc.any()) and np.all(r == 0.0) and np.all(info["gains"] == 0.0)
    obs, r, term, trunc, _ = venv.step(acts[0])  # and the new episode goes on
    assert np.abs(obs[:, -3:]).max() > 0 and np.all(r != 0.0) and not trunc.any()


def test_vector_wrappers_of_gymnasium_work_on_the_next_step_env():
    from gymnasium.wrappers.vector import NormalizeObservation, TransformObservation

    venv = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", **CONFIG)
    venv = TransformObservation(NormalizeObservation(venv), lambda o: np.clip(o, -5, 5), venv.observation_space)
    obs, _ = venv.reset(seed=0)
    for _ in range(12):  # through an automatic reset
        obs, r, term, trunc, _ = venv.step(np.zeros((2, 3), np.float32))
    assert obs.shape == (2, OBS) and np.isfinite(obs).all() and np.abs(obs).max() <= 5


def test_reset_mask_and_one_seed_per_environment():
    venv = GainVectorEnv(num_envs=4, **{**CONFIG, "amp_range": (5.0, 15.0)})
    obs, _ = venv.reset(seed=[7, 8, 7, None])
    np.testing.assert_array_equal(obs[0], obs[2])  # the same seed, the same episode
    assert not np.array_equal(obs[0], obs[1])
    first = [venv.step(np.full((4, 3), 0.5, np.float32))[0] for _ in range(3)][-1]
    mask = np.array([False, True, False, False])
    again, _ = venv.reset(seed=[0, 8, 0, 0], options={"reset_mask": mask})
    np.testing.assert_array_equal(again[1], obs[1])  # env 1 starts again from seed 8
    np.testing.assert_array_equal(again[~mask], first[~mask])  # the others keep their episodes
    assert np.isfinite(venv.step(np.full((4, 3), 0.5, np.float32))[0]).all()
    with pytest.raises(ValueError, match="reset_mask"):
        venv.reset(options={"reset_mask": [True]})
    with pytest.raises(ValueError, match="one seed per environment"):
        venv.reset(seed=[1, 2])


def test_render_rgb_array_is_the_episode_as_a_space_time_picture():
    env = gym.make(ENV_ID, render_mode="rgb_array", **{**CONFIG, "amp_range": (10.0, 10.0)})
    env.reset(seed=0)
    frames = [env.render()]
    for _ in range(10):
        env.step(np.full(3, -0.5, np.float32))
        frames.append(env.render())
    assert all(f.shape == (200, 400, 3) and f.dtype == np.uint8 for f in frames)
    grey = [np.mean(np.all(f == 217, axis=-1)) for f in frames]  # steps not reached yet are grey
    assert grey[0] > 0.85 and grey[-1] < 0.01 and all(a >= b for a, b in zip(grey, grey[1:], strict=False))
    assert frames[-1].std() > 5  # the wave is drawn, not one colour
    venv = GainVectorEnv(num_envs=2, render_mode="rgb_array", **CONFIG)
    venv.reset(seed=0)
    venv.step(np.zeros((2, 3), np.float32))
    images = venv.render()
    assert len(images) == 2 and images[0].shape == (200, 400, 3)
    assert GainEnv(**CONFIG).render() is None
    with pytest.raises(ValueError, match="render_mode"):
        GainEnv(render_mode="human", **CONFIG)


def test_vector_env_step_matches_single_env_spaces():
    venv = GainVectorEnv(num_envs=2, **CONFIG)
    env = GainEnv(**CONFIG)
    assert venv.single_observation_space == env.observation_space
    with pytest.raises(gym.error.ResetNeeded):
        venv.step(np.zeros((2, 3), np.float32))


@pytest.mark.slow  # end to end (seconds to tens of seconds): CI's slow tier
def test_sb3_vec_env_adapter_and_example(tmp_path):
    need("stable_baselines3")
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
    with pytest.raises(ValueError, match="SAME_STEP"):
        SB3VecEnv(GainVectorEnv(num_envs=2, **CONFIG))
    from stable_baselines3.common.env_util import make_vec_env

    made = make_vec_env(ENV_ID, n_envs=2, env_kwargs=CONFIG)  # SB3's own helper: render_mode="rgb_array"
    assert made.reset().shape == (2, OBS) and made.render_mode == "rgb_array"
    assert made.get_images()[0].shape == (200, 400, 3)

    spec = importlib.util.spec_from_file_location("sb3_ppo", REPO / "examples" / "sb3_ppo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    saved = tmp_path / "sb3.zip"
    res = mod.main(["--n-points", str(N), "--horizon-s", "1", "--num-envs", "8", "--n-steps", "16",
                    "--total-timesteps", "256", "--save", str(saved)])
    assert res["num_timesteps"] >= 256 and len(res["returns"]) > 0 and np.isfinite(res["returns"]).all()
    # the saved model as a controller (evaluate.py --controller sb3=examples/sb3_ppo.py:controller:PATH): it
    # applies what SB3's predict chooses for the environment's own observation
    from jaxtraffic import simulate
    from jaxtraffic.control.gain_policy import policy_features
    from jaxtraffic.model.params import equilibrium
    from jaxtraffic.sim import initial_state, paper_initial_condition

    ctrl, grid = mod.controller(str(saved))
    ep = GainEnv(n_points=N, horizon_s=1.0).env_params  # the environment it was trained on
    plant = ep.traffic
    assert grid.n_points == N and np.isfinite(float(simulate(plant, ctrl, n_steps=20).metrics["J_comfort"]))
    obs = initial_state(plant, *paper_initial_condition(plant)).observation(plant)
    x = np.asarray(policy_features(obs, np.zeros(3, np.float32), plant, ep.gain_max, equilibrium(plant),
                                   ep.obs_segments))
    _, gains = ctrl.act(ctrl.init(obs, plant), obs, plant, None)
    a = np.clip(res["model"].predict(x, deterministic=True)[0], -1, 1)
    np.testing.assert_allclose(np.asarray(gains), ep.gain_filter * a * np.asarray(ep.gain_max), rtol=1e-4, atol=1e-6)

