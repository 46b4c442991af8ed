"""PPO maths (GAE, clipped surrogate, log-probabilities, running statistics), the truncation
bootstrap in the rollout, and learning on toy environments with GainEnv's interface."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from jaxtraffic.learn import env as learn_env
from jaxtraffic.learn import ppo
from jaxtraffic.learn.env import TrafficEnv
from jaxtraffic.learn.ppo import algorithm
from jaxtraffic.model.params import TrafficParams

# ----------------------------------------------------------------------------------------- GAE


def test_gae_hand_computed_with_done_in_the_middle():
    # T = 4, episode ends after step 1 (dones[1] = 1); gamma = 0.9, lambda = 0.8 (gamma lambda = 0.72)
    r = jnp.array([1.0, 2.0, 3.0, 4.0])
    v = jnp.array([0.5, 1.0, 1.5, 2.0])
    d = jnp.array([0.0, 1.0, 0.0, 0.0])
    adv, target = ppo.compute_gae(r, v, d, jnp.asarray(3.0), 0.9, 0.8)
    # delta_3 = 4 + 0.9*3 - 2 = 4.7;           A_3 = 4.7
    # delta_2 = 3 + 0.9*2 - 1.5 = 3.3;         A_2 = 3.3 + 0.72*4.7 = 6.684
    # delta_1 = 2 + 0 - 1 = 1 (done: no V);    A_1 = 1 (the trace is cut)
    # delta_0 = 1 + 0.9*1 - 0.5 = 1.4;         A_0 = 1.4 + 0.72*1 = 2.12
    np.testing.assert_allclose(adv, [2.12, 1.0, 6.684, 4.7], rtol=1e-6)
    np.testing.assert_allclose(target, [2.62, 2.0, 8.184, 6.7], rtol=1e-6)


def test_gae_batched_columns_are_independent():
    r = jnp.array([[1.0, 0.0], [2.0, 1.0], [3.0, -1.0], [4.0, 2.0]])
    v = jnp.array([[0.5, 0.0], [1.0, 0.5], [1.5, 0.0], [2.0, 1.0]])
    d = jnp.array([[0, 0], [1, 0], [0, 1], [0, 0]], bool)
    adv, _ = ppo.compute_gae(r, v, d, jnp.array([3.0, -2.0]), 0.9, 0.8)
    np.testing.assert_allclose(adv[:, 0], [2.12, 1.0, 6.684, 4.7], rtol=1e-6)
    # column 1 by hand: delta_3 = 2 - 1.8 - 1 = -0.8; delta_2 = -1 - 0 = -1 (done); delta_1 = 1 + 0 - 0.5 = 0.5;
    # delta_0 = 0 + 0.45 - 0 = 0.45.  A_3 = -0.8, A_2 = -1, A_1 = 0.5 - 0.72 = -0.22, A_0 = 0.45 - 0.1584
    np.testing.assert_allclose(adv[:, 1], [0.2916, -0.22, -1.0, -0.8], rtol=1e-5)


def test_gae_truncation_bootstraps_terminal_value():
    # truncated after step 1 with V(terminal_obs) = 5: the rollout folds gamma V(terminal) into the
    # reward and marks the step done, so the target is r + gamma V(terminal), not r (termination).
    gamma, lam, v_term = 0.9, 0.8, 5.0
    r = jnp.array([1.0, 2.0 + gamma * v_term, 3.0, 4.0])
    v = jnp.array([0.5, 1.0, 1.5, 2.0])
    d = jnp.array([0.0, 1.0, 0.0, 0.0])
    adv, target = ppo.compute_gae(r, v, d, jnp.asarray(3.0), gamma, lam)
    assert float(target[1]) == pytest.approx(2.0 + gamma * v_term)  # 6.5
    assert float(adv[1]) == pytest.approx(6.5 - 1.0)
    assert float(adv[0]) == pytest.approx(1.4 + gamma * lam * 5.5)  # the trace continues into step 1
    np.testing.assert_allclose(adv[2:], [6.684, 4.7], rtol=1e-6)  # the next episode is unaffected


# ------------------------------------------------------------------------- clipped surrogate


def _np_surrogate(ratio, adv, eps):
    return -np.mean(np.minimum(ratio * adv, np.clip(ratio, 1 - eps, 1 + eps) * adv))


@pytest.mark.parametrize("ratio, adv, expected", [
    (1.1, 2.0, -2.2),     # inside the range, A > 0: ratio A
    (0.9, -2.0, 1.8),     # inside, A < 0
    (1.5, 2.0, -2.4),     # above 1 + eps, A > 0: clipped to 1.2 A
    (1.5, -2.0, 3.0),     # above, A < 0: the unclipped (worse) ratio A
    (0.5, 2.0, -1.0),     # below 1 - eps, A > 0: unclipped 0.5 A
    (0.5, -2.0, 1.6),     # below, A < 0: clipped to 0.8 A
])
def test_clipped_surrogate_single_samples(ratio, adv, expected):
    eps = 0.2
    logp = jnp.log(jnp.asarray([ratio]))
    got = ppo.clipped_surrogate(logp, jnp.zeros(1), jnp.asarray([adv]), eps)
    assert float(got) == pytest.approx(expected, rel=1e-6)
    assert float(got) == pytest.approx(_np_surrogate(np.array([ratio]), np.array([adv]), eps), rel=1e-6)
    # clipped terms carry no gradient; unclipped ones d/dlogp = -ratio A
    grad = jax.grad(lambda lp: ppo.clipped_surrogate(lp, jnp.zeros(1), jnp.asarray([adv]), eps))(logp)
    clipped = (ratio > 1 + eps and adv > 0) or (ratio < 1 - eps and adv < 0)
    assert float(grad[0]) == pytest.approx(0.0 if clipped else -ratio * adv, rel=1e-5, abs=1e-7)


def test_clipped_surrogate_batch_matches_numpy():
    rng = np.random.default_rng(0)
    ratio = rng.uniform(0.3, 1.8, 257)
    adv = rng.normal(size=257)
    old = rng.normal(size=257)
    logp = old + np.log(ratio)
    for eps in (0.1, 0.2, 0.3):
        got = ppo.clipped_surrogate(jnp.asarray(logp), jnp.asarray(old), jnp.asarray(adv), eps)
        np.testing.assert_allclose(got, _np_surrogate(ratio, adv, eps), rtol=1e-5)


def test_gaussian_log_prob_and_entropy():
    rng = np.random.default_rng(1)
    x, mu = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    sig = rng.uniform(0.1, 2.0, size=(5, 3))
    ref = np.sum(-0.5 * ((x - mu) / sig) ** 2 - np.log(sig * np.sqrt(2 * np.pi)), axis=-1)
    np.testing.assert_allclose(ppo.gaussian_log_prob(jnp.asarray(x), jnp.asarray(mu), jnp.asarray(sig)), ref,
                               rtol=1e-5)
    np.testing.assert_allclose(ppo.gaussian_entropy(jnp.asarray(sig)),
                               np.sum(0.5 * np.log(2 * np.pi * np.e * sig**2), axis=-1), rtol=1e-5)


def test_running_stats_match_numpy():
    rng = np.random.default_rng(2)
    batches = [rng.normal(loc=3.0, scale=2.0, size=(n, 4)) for n in (50, 70, 30)]
    s = ppo.RunningStats.create(4)
    for b in batches:
        s = s.update(jnp.asarray(b.mean(0)), jnp.asarray(b.var(0)), jnp.asarray(float(len(b))))
    allx = np.concatenate(batches)
    np.testing.assert_allclose(s.mean, allx.mean(0), rtol=1e-4)
    np.testing.assert_allclose(s.var, allx.var(0), rtol=1e-3)
    z = s.normalize(jnp.asarray(allx))
    np.testing.assert_allclose(np.mean(np.asarray(z), 0), 0.0, atol=1e-3)


# ------------------------------------------------------------------------------ toy environments


@struct.dataclass
class ToyParams:
    target: jax.Array
    horizon: int = 4


@struct.dataclass
class ToyState:
    t: jax.Array


class ToyEnv:
    """A trivially learnable task with GainEnv's interface: observation 0, reward
    -sum_i (a_i - target_i)^2, episodes of ``horizon`` steps ended by truncation. The optimal policy
    mean is ``target``. The truncated step pays reward 0 and reports a distinctive
    ``terminal_obs`` (all 5), so the bootstrap the rollout adds, gamma V(terminal_obs), can be read
    off exactly."""

    action_size = 3
    TERMINAL = 5.0

    @staticmethod
    def obs_size(params):
        return 2

    @staticmethod
    def reset(key, params):
        return jnp.zeros(2), ToyState(t=jnp.zeros((), jnp.int32))

    @staticmethod
    def step(key, state, action, params):
        t = state.t + 1
        truncated = t >= params.horizon
        r = jnp.where(truncated, 0.0, -jnp.sum((action - params.target) ** 2))
        info = {"terminal_obs": jnp.where(truncated, ToyEnv.TERMINAL, 0.0) * jnp.ones(2), "truncated": truncated,
                "terminated": jnp.zeros((), bool)}
        return jnp.zeros(2), ToyState(t=jnp.where(truncated, 0, t)), r, truncated, info


TOY_CFG = ppo.PPOConfig(num_envs=8, num_steps=8, update_epochs=4, num_minibatches=2, updates_per_chunk=5,
                        hidden=(16,), lr=1e-2, init_sigma=0.5, gamma=0.9, reward_scale=0.5)
TARGET = np.array([0.6, -0.4, 0.3])


@pytest.fixture(scope="module")
def toy_run():
    """Two chunks of 5 PPO updates on ToyEnv (one compilation shared by the tests below), with a
    spy on ``compute_gae`` recording the (rewards, values, dones) of every update."""
    seen = []
    orig = ppo.compute_gae

    def spy(rewards, values, dones, last_value, gamma, lam):
        jax.debug.callback(lambda *a: seen.append([np.asarray(x) for x in a]), rewards, values, dones)
        return orig(rewards, values, dones, last_value, gamma, lam)

    cfg = TOY_CFG
    net = cfg.network()
    out = {"seen": seen, "means": [], "metrics": []}

    def policy(r):
        rep = jax.tree.map(lambda x: x[0, 0], r)  # device 0, seed 0
        mean, _, v_zero = net.apply(rep.params, rep.stats.normalize(jnp.zeros(2)))
        _, _, v_term = net.apply(rep.params, rep.stats.normalize(jnp.full(2, ToyEnv.TERMINAL)))
        return np.asarray(mean), float(v_zero), float(v_term)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(algorithm, "compute_gae", spy)
        init, train_chunk = ppo.make_train(cfg, ToyParams(target=jnp.asarray(TARGET)), env=ToyEnv)
        runner = init(jax.random.PRNGKey(0))
        mean0, out["v_zero"], out["v_term"] = policy(runner)
        out["means"].append(mean0)
        for _ in range(2):
            runner, m = train_chunk(runner)
            jax.block_until_ready(m)
            out["means"].append(policy(runner)[0])
            out["metrics"].append(jax.tree.map(np.asarray, m))
    return out


def test_rollout_bootstraps_truncated_steps(toy_run):
    """The rewards PPO feeds to GAE are reward_scale r + gamma V(terminal_obs) on truncated steps
    (checked on the first update, whose parameters are the initial ones)."""
    cfg = TOY_CFG
    assert len(toy_run["seen"]) == 2 * cfg.updates_per_chunk
    rewards, values, dones = (x.reshape(cfg.num_steps, cfg.num_envs) for x in toy_run["seen"][0])
    v_term, v_zero = toy_run["v_term"], toy_run["v_zero"]
    assert abs(v_term - v_zero) > 1e-3  # the terminal observation has its own value
    assert dones.any() and not dones.all()
    # truncated steps: raw reward 0, so the training reward is exactly gamma V(terminal_obs)
    np.testing.assert_allclose(rewards[dones], cfg.gamma * v_term, rtol=1e-5, atol=1e-6)
    # other steps: reward_scale * r <= 0, no bootstrap term
    assert np.all(rewards[~dones] <= 0.0) and np.all(rewards[~dones] > -0.5 * 20)
    np.testing.assert_allclose(values, v_zero, rtol=1e-5, atol=1e-6)
    # make_train staggers the initial episode ages; each environment then truncates every 4 steps
    for col in dones.T:
        assert col.sum() == 2 and np.diff(np.flatnonzero(col)).tolist() == [4]


def test_ppo_updates_move_policy_toward_target(toy_run):
    dist = [np.linalg.norm(m - TARGET) for m in toy_run["means"]]
    r1, r2 = (m["mean_reward"][0] for m in toy_run["metrics"])
    assert dist[1] < 0.8 * dist[0], dist  # 5 updates
    assert dist[2] < 0.4 * dist[0], dist  # 10 updates
    assert r2[-1] > r1[0] + 0.1, (r1, r2)  # the expected reward -|mu - target|^2 - sum sigma^2 improves
    assert all(np.all(np.isfinite(m["value_loss"])) for m in toy_run["metrics"])


def test_make_train_rejects_indivisible_batch():
    cfg = ppo.PPOConfig(num_envs=3, num_steps=5, num_minibatches=4)
    with pytest.raises(ValueError, match="num_minibatches"):
        ppo.make_train(cfg, learn_env.make_env_params(TrafficParams(n_points=21, delay=0.5)), env=learn_env.TrafficEnv)


def test_learning_rate_is_constant():
    sched = ppo.lr_schedule(TOY_CFG)
    assert [float(sched(jnp.asarray(c))) for c in (0, 7, 1000)] == [pytest.approx(1e-2)] * 3
    with pytest.raises(ValueError, match="lr = 0.0: must be > 0.0"):
        ppo.check_ppo_config(TOY_CFG.replace(lr=0.0))


# ------------------------------------------------------------------------------ several seeds
SEVERAL_SEEDS = """
import json
import jax, jax.numpy as jnp, numpy as np
from jaxtraffic.learn import env as learn_env
from jaxtraffic.learn.ppo import algorithm
from jaxtraffic.learn import ppo
from jaxtraffic.model.params import TrafficParams

cfg = ppo.PPOConfig(num_envs=16, num_steps=8, update_epochs=1, num_minibatches=2, updates_per_chunk=1, num_seeds=2)
ep = learn_env.make_env_params(TrafficParams(n_points=21, delay=4.0))
init, train_chunk = ppo.make_train(cfg, ep, env=learn_env.TrafficEnv)
for seed in range(4):  # the deadlock was a race: give it several chances
    runner = jax.block_until_ready(init(jax.random.PRNGKey(seed)))
runner, m = train_chunk(runner)
jax.block_until_ready((runner, m))
# lax.map over the seeds gives each seed the network the one-seed vmap gives it (bit for bit) and
# the same environments (a different XLA program: equal to a few float32 ulps)
one = jax.jit(lambda ks: algorithm._init_seeds(
    lambda k: algorithm._init_seed(cfg, learn_env.TrafficEnv, ep, 16, k, jnp.int32(0)), ks))
keys = jax.random.split(jax.random.PRNGKey(3), 2)
both = init(jax.random.PRNGKey(3))
alone = [one(keys[i:i + 1]) for i in range(2)]
pairs = [(np.asarray(a)[0, i], np.asarray(b)[0]) for i in range(2)
         for a, b in zip(jax.tree.leaves(both.params), jax.tree.leaves(alone[i].params), strict=True)]
close = [(np.asarray(a)[0, i], np.asarray(b)[0]) for i in range(2)
         for a, b in zip(jax.tree.leaves(both), jax.tree.leaves(alone[i]), strict=True)]
print("RESULT " + json.dumps({"shape": list(m["mean_reward"].shape),
                              "same_params": all(np.array_equal(a, b) for a, b in pairs),
                              "close": all(np.allclose(a, b, rtol=1e-5, atol=1e-6) for a, b in close),
                              "finite": all(bool(np.all(np.isfinite(x))) for x in jax.tree.leaves(m))}))
"""


@pytest.mark.slow
def test_several_seeds_do_not_hang():
    """Two seeds, the default (64, 64) networks: ``init`` and one chunk finish .
    Under ``vmap`` the orthogonal initialisers were batched LAPACK QRs, which jaxlib 0.10 splits
    over XLA:CPU's intra-op pool and waits for; on a 2-core machine this deadlocked ``init``.
    Run in a subprocess with a timeout, so that a regression fails instead of hanging the suite."""
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": os.pathsep.join(
        filter(None, [str(repo), os.environ.get("PYTHONPATH", "")]))}
    try:
        proc = subprocess.run([sys.executable, "-c", SEVERAL_SEEDS], cwd=repo, env=env, capture_output=True,
                              text=True, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.fail("two-seed init + one chunk did not finish in 300 s (XLA:CPU LAPACK thread-pool deadlock?)")
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
    assert line, proc.stdout[-2000:]
    res = json.loads(line[0][len("RESULT "):])
    assert res["shape"] == [2, 1] and res["finite"]
    assert res["same_params"] and res["close"]


def test_several_seeds_init_has_no_batched_lapack_call():
    """The deterministic side of the test above: in the two-seed ``init`` program every LAPACK
    custom call (the orthogonal initialisers' QRs) works on one matrix, never on a batch, so
    jaxlib cannot split it over the thread pool (the race above needs it to)."""
    cfg = ppo.PPOConfig(num_envs=8, num_seeds=2)
    ep = learn_env.make_env_params(TrafficParams(n_points=21, delay=4.0))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    text = jax.jit(lambda ks: algorithm._init_seeds(
        lambda k: algorithm._init_seed(cfg, TrafficEnv, ep, 8, k, jnp.int32(0)), ks)).lower(keys).as_text()
    shapes = re.findall(r"custom_call @lapack_\w+\(.*: \(tensor<([0-9x]+)x[a-z]+[0-9]*>", text)
    n_in = learn_env.obs_size(ep)  # the first layer's QR is of its kernel or of its transpose, the taller of the two
    assert {f"{max(n_in, 64)}x{min(n_in, 64)}", "64x64", "64x3", "64x1"} <= set(shapes), shapes  # geqrf + orgqr
    assert all(s.count("x") == 1 for s in shapes), shapes
