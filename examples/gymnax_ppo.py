#!/usr/bin/env python
"""Train jaxtraffic's gain environment with a third-party-style JAX PPO, through gymnax alone.

The PPO below is a purejaxrl-style loop (continuous actions, one jit-compiled ``train`` function,
``lax.map`` over seeds: a ``vmap`` would batch the orthogonal initialisers' QR decompositions, which
can deadlock XLA:CPU's thread pool on small machines, see ``learn/ppo/algorithm.py``) written against
gymnax's interface only: it knows nothing of jaxtraffic but the environment's constructor. It
runs the environment under gymnax's wrappers
(``LogWrapper(FlattenObservationWrapper(env))``), samples Gaussian actions that the environment
clips to its [-1, 1]^3 normalised-gain box, and bootstraps truncated episodes from
``info["final_observation"]`` (gymnax 1.0's six-value step).

    pip install -e ".[gymnax]"
    python examples/gymnax_ppo.py --n-points 51 --num-updates 50      # a few minutes on 2 CPU cores
    python examples/gymnax_ppo.py --help

Prints the mean return of the episodes completed in the last updates (LogWrapper's
``returned_episode_returns``) and the throughput. ``tests/test_ecosystem_gymnax.py`` runs it on a
21-point grid for a few updates.
"""

from __future__ import annotations

import argparse
import time

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState
from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper

from jaxtraffic.ecosystem.gymnax_env import GainGymnaxEnv


class ActorCritic(nn.Module):
    action_dim: int
    hidden: int = 64

    @nn.compact
    def __call__(self, x):
        init = nn.initializers.orthogonal
        a = nn.tanh(nn.Dense(self.hidden, kernel_init=init(np.sqrt(2)))(x))
        a = nn.tanh(nn.Dense(self.hidden, kernel_init=init(np.sqrt(2)))(a))
        mean = nn.Dense(self.action_dim, kernel_init=init(0.01))(a)
        log_std = self.param("log_std", nn.initializers.constant(np.log(0.3)), (self.action_dim,))
        c = nn.tanh(nn.Dense(self.hidden, kernel_init=init(np.sqrt(2)))(x))
        c = nn.tanh(nn.Dense(self.hidden, kernel_init=init(np.sqrt(2)))(c))
        return mean, jnp.exp(log_std), jnp.squeeze(nn.Dense(1, kernel_init=init(1.0))(c), -1)


def log_prob(x, mean, std):
    return jnp.sum(-0.5 * ((x - mean) / std) ** 2 - jnp.log(std) - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def make_train(cfg: dict, env, env_params):
    env = LogWrapper(FlattenObservationWrapper(env))
    n_act = env.action_space(env_params).shape[0]
    net = ActorCritic(n_act)
    batch = cfg["num_envs"] * cfg["num_steps"]
    mb = batch // cfg["num_minibatches"]
    n_opt = cfg["num_updates"] * cfg["update_epochs"] * cfg["num_minibatches"]
    tx = optax.chain(optax.clip_by_global_norm(0.5),
                     optax.adam(optax.linear_schedule(cfg["lr"], 0.1 * cfg["lr"], n_opt), eps=1e-5))

    def train(key):
        key, k_net, k_env = jax.random.split(key, 3)
        obs_shape = env.observation_space(env_params).shape
        state = TrainState.create(apply_fn=net.apply, params=net.init(k_net, jnp.zeros(obs_shape)), tx=tx)
        obs, env_state = jax.vmap(env.reset, (0, None))(jax.random.split(k_env, cfg["num_envs"]), env_params)

        def update(runner, _):
            def env_step(carry, _):
                state, env_state, obs, key = carry
                key, k_act, k_step = jax.random.split(key, 3)
                mean, std, value = net.apply(state.params, obs)
                action = mean + std * jax.random.normal(k_act, mean.shape)
                obs2, env_state, reward, term, trunc, info = jax.vmap(env.step, (0, 0, 0, None))(
                    jax.random.split(k_step, cfg["num_envs"]), env_state, action, env_params)
                _, _, v_final = net.apply(state.params, info["final_observation"])
                r = cfg["reward_scale"] * reward + cfg["gamma"] * v_final * trunc  # bootstrap truncation
                tr = {"obs": obs, "action": action, "logp": log_prob(action, mean, std), "value": value,
                      "reward": r, "done": term | trunc, "ret": info["returned_episode_returns"],
                      "ended": info["returned_episode"]}
                return (state, env_state, obs2, key), tr

            (state, env_state, obs, key), traj = jax.lax.scan(env_step, runner, None, cfg["num_steps"])
            _, _, last_v = net.apply(state.params, obs)

            def gae(carry, t):
                adv, next_v = carry
                delta = t["reward"] + cfg["gamma"] * next_v * (1 - t["done"]) - t["value"]
                adv = delta + cfg["gamma"] * cfg["gae_lambda"] * (1 - t["done"]) * adv
                return (adv, t["value"]), adv

            _, adv = jax.lax.scan(gae, (jnp.zeros_like(last_v), last_v), traj, reverse=True)
            data = {k: traj[k].reshape((batch,) + traj[k].shape[2:]) for k in ("obs", "action", "logp", "value")}
            data.update(adv=adv.reshape(-1), target=(adv + traj["value"]).reshape(-1))

            def loss_fn(params, b):
                mean, std, value = net.apply(params, b["obs"])
                ratio = jnp.exp(log_prob(b["action"], mean, std) - b["logp"])
                a = (b["adv"] - b["adv"].mean()) / (b["adv"].std() + 1e-8)
                pg = -jnp.mean(jnp.minimum(ratio * a, jnp.clip(ratio, 1 - cfg["clip_eps"], 1 + cfg["clip_eps"]) * a))
                return pg + 0.5 * 0.5 * jnp.mean((value - b["target"]) ** 2)

            def epoch(carry, k):
                def minibatch(state, b):
                    loss, grads = jax.value_and_grad(loss_fn)(state.params, b)
                    return state.apply_gradients(grads=grads), loss

                perm = jax.random.permutation(k, batch)
                shuffled = jax.tree.map(lambda x: x[perm].reshape((cfg["num_minibatches"], mb) + x.shape[1:]), data)
                return jax.lax.scan(minibatch, carry, shuffled)

            key, k_perm = jax.random.split(key)
            state, losses = jax.lax.scan(epoch, state, jax.random.split(k_perm, cfg["update_epochs"]))
            ended = traj["ended"].sum()
            metrics = {"loss": losses.mean(), "episodes": ended,
                       "episode_return": jnp.where(ended > 0, (traj["ret"] * traj["ended"]).sum() / ended, jnp.nan)}
            return (state, env_state, obs, key), metrics

        runner, metrics = jax.lax.scan(update, (state, env_state, obs, key), None, cfg["num_updates"])
        return runner[0], metrics

    return train


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-points", type=int, default=51, help="grid points of the traffic PDE")
    ap.add_argument("--horizon-s", type=float, default=10.0, help="episode length, s")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--num-steps", type=int, default=100, help="rollout steps per update")
    ap.add_argument("--num-updates", type=int, default=50)
    ap.add_argument("--update-epochs", type=int, default=4)
    ap.add_argument("--num-minibatches", type=int, default=4)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--num-seeds", type=int, default=2, help="independent seeds, one jit(lax.map(train))")
    args = ap.parse_args(argv)
    cfg = {"num_envs": args.num_envs, "num_steps": args.num_steps, "num_updates": args.num_updates,
           "update_epochs": args.update_epochs, "num_minibatches": args.num_minibatches, "lr": args.lr,
           "gamma": 0.995, "gae_lambda": 0.95, "clip_eps": 0.2, "reward_scale": 0.01}
    env = GainGymnaxEnv(n_points=args.n_points, horizon_s=args.horizon_s)
    train = jax.jit(lambda keys: jax.lax.map(make_train(cfg, env, env.default_params), keys))
    keys = jax.random.split(jax.random.PRNGKey(0), args.num_seeds)
    t0 = time.perf_counter()
    compiled = train.lower(keys).compile()
    t1 = time.perf_counter()
    _, metrics = jax.block_until_ready(compiled(keys))
    t2 = time.perf_counter()
    metrics = jax.tree.map(np.asarray, metrics)
    steps = args.num_seeds * args.num_updates * args.num_envs * args.num_steps
    ret = metrics["episode_return"]
    print(f"{env.name}: {args.num_seeds} seed(s) x {args.num_updates} updates x {args.num_envs} envs x "
          f"{args.num_steps} steps; compile {t1 - t0:.1f} s, train {t2 - t1:.1f} s "
          f"({steps / (t2 - t1):,.0f} env steps/s)")
    for name, col in (("first", 0), ("last", -1)):
        print(f"  mean episode return, {name} update with completed episodes, per seed: "
              f"{np.round([r[np.isfinite(r)][col] if np.isfinite(r).any() else np.nan for r in ret], 3)}")
    return {"metrics": metrics, "env_steps": steps, "steps_per_s": steps / (t2 - t1)}


if __name__ == "__main__":
    main()
