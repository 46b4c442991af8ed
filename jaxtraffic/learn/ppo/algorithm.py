"""Pure-JAX PPO for the gain policy, in the style of purejaxrl.

``make_train(config, env_params)`` returns ``(init, train_chunk)``:
  * ``init(key) -> Runner``: network, optimiser, environments and observation statistics for
    ``config.num_seeds`` independent seeds (a leading seed axis on every leaf);
  * ``train_chunk(runner) -> (runner, metrics)``: ``config.updates_per_chunk`` PPO updates as
    one jit-compiled function: an outer ``lax.scan`` over updates, inside it a ``lax.scan``
    rollout of ``num_steps`` vmapped environment steps, GAE, and ``update_epochs`` x
    ``num_minibatches`` Adam steps (nested ``lax.scan``). Metrics are reduced per update
    (shape (seeds, updates_per_chunk)); no per-step arrays leave the scan.
The environment batch is split over a one-axis mesh of devices (``train_mesh``: by default every
device of every process, ``jax.devices()``): ``init`` and ``train_chunk`` are ``jax.jit`` of
``jax.shard_map`` with the per-device body, one code path for one device, many devices and many
processes. Gradients and observation statistics are averaged across devices (``lax.pmean``), so
parameters stay replicated. Seeds are a ``vmap`` inside each device. (This replaced ``pmap``,
with bit-identical results on 1 and 2 devices and the same speed: docs/model.md section 19.2.)

Config is a pytree (rejax style): shape-setting fields are static, float hyperparameters are
traced leaves, so changing a learning rate or a clip range does not recompile.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxtraffic.control.gain_policy import normalize_obs
from jaxtraffic.control.networks import SMALL_HIDDEN, ActorCritic, actor_critic_apply
from jaxtraffic.fields import check_fields, hyper
from jaxtraffic.learn.ppo.losses import Batch, compute_gae, gaussian_log_prob, ppo_loss
from jaxtraffic.sim.sharding import local_copy

Array = jax.Array
AXIS = "dev"


@struct.dataclass
class PPOConfig:
    """PPO hyperparameters (defaults: the training defaults of ``train.py``). Static: sizes and counts.
    Traced: the floats."""

    num_envs: int = hyper(256, lo=1, static=True, help="parallel environments per seed (population member)")
    num_steps: int = hyper(100, lo=1, static=True, help="rollout steps per update (100 = 10 s)")
    update_epochs: int = hyper(4, lo=1, static=True, help="epochs per update")
    num_minibatches: int = hyper(4, lo=1, static=True, help="minibatches per epoch")
    updates_per_chunk: int = hyper(3, lo=1, static=True, help="updates per jit-compiled chunk")
    num_seeds: int = hyper(1, lo=1, static=True, help="independent seeds (population members) trained at once")
    # (algo "both": a run's gradient trainer takes its network from here, ``runs.config``)
    hidden: tuple[int, ...] = hyper(SMALL_HIDDEN, lo=1, static=True, algo="both",
                                    help="hidden layer sizes (actor, critic)")
    init_sigma: float = hyper(0.3, lo=0.0, lo_open=True, static=True, help="initial action std (pre-tanh)")
    lr: float = hyper(1e-3, lo=0.0, lo_open=True, help="Adam learning rate")
    gamma: float = hyper(0.995, lo=0.0, lo_open=True, hi=1.0, help="discount per step (dt)")
    gae_lambda: float = hyper(0.95, lo=0.0, hi=1.0, help="GAE lambda")
    clip_eps: float = hyper(0.2, lo=0.0, lo_open=True, help="PPO clip range of the probability ratio")
    ent_coef: float = hyper(0.0, lo=0.0, help="entropy bonus weight")
    vf_coef: float = hyper(0.5, lo=0.0, help="value loss weight")
    max_grad_norm: float = hyper(0.5, lo=0.0, lo_open=True, help="global gradient-norm clip")
    reward_scale: float = hyper(0.01, lo=0.0, lo_open=True, help="reward multiplier for learning")

    def network(self, n_actions: int = 3) -> ActorCritic:
        return ActorCritic(hidden=tuple(self.hidden), init_sigma=self.init_sigma,
                           n_actions=n_actions)

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.num_steps


@struct.dataclass
class RunningStats:
    """Running mean / variance of observations (parallel Welford update).

    Kept rather than a library's normaliser (gymnasium's ``NormalizeObservation``, SB3's
    ``VecNormalize``, which live outside the compiled program in numpy): it is a pytree inside the
    jit-compiled chunk, averaged across devices with ``lax.pmean``, saved in the checkpoint, and
    shipped with the deployed policy (``policy_controller`` takes its mean and variance)."""

    mean: Array
    var: Array
    count: Array

    @classmethod
    def create(cls, size: int) -> RunningStats:
        return cls(jnp.zeros(size), jnp.ones(size), jnp.asarray(1e-4))

    def normalize(self, x: Array) -> Array:
        return normalize_obs(x, self.mean, self.var)

    def update(self, batch_mean: Array, batch_var: Array, batch_count: Array) -> RunningStats:
        delta = batch_mean - self.mean
        tot = self.count + batch_count
        mean = self.mean + delta * batch_count / tot
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / tot
        return RunningStats(mean, m2 / tot, tot)


@struct.dataclass
class Runner:
    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> Runner: ...

    params: Any
    opt_state: Any
    env_state: Any
    obs: Array
    stats: RunningStats
    key: Array
    update: Array


# --------------------------------------------------------------------------- pure PPO maths
def check_ppo_config(ppo_config: PPOConfig) -> None:
    """Reject hyperparameters that make no sense (ValueError): each field against the range in its
    metadata (``jaxtraffic.fields.hyper``)."""
    check_fields(ppo_config)


def lr_schedule(ppo_config: PPOConfig) -> optax.Schedule:
    """The Adam step size as a function of the optimiser's step count: the constant ``lr`` (a schedule, so
    that the optimiser's state holds the step count, as the checkpoints always have)."""
    return lambda count: ppo_config.lr


def make_optimizer(ppo_config: PPOConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(ppo_config.max_grad_norm),
                       optax.inject_hyperparams(optax.adam)(learning_rate=lr_schedule(ppo_config), eps=1e-5))


# --------------------------------------------------------------------------- training
def _init_seed(ppo_config: PPOConfig, env, env_params, num_envs: int, key: Array, dev: Array) -> Runner:
    """Runner of one seed on device ``dev``: the network and the key are the same on every
    device (replicated); the environments differ."""
    k_net, k_env, k_run = jax.random.split(key, 3)
    net = ppo_config.network(env.action_size)
    params = net.init(k_net, jnp.zeros((env.obs_size(env_params),)))
    env_keys = jax.random.split(jax.random.fold_in(k_env, dev), num_envs)
    obs, env_state = jax.vmap(env.reset, (0, None))(env_keys, env_params)
    if hasattr(env_state, "t") and hasattr(env_params, "horizon"):
        # stagger episode ends so a batch does not see every environment at the same age
        ages = jax.random.randint(jax.random.fold_in(k_env, -1 - dev), (num_envs,), 0, env_params.horizon)
        env_state = env_state.replace(t=ages.astype(env_state.t.dtype))
    return Runner(params=params, opt_state=make_optimizer(ppo_config).init(params), env_state=env_state, obs=obs,
                  stats=RunningStats.create(env.obs_size(env_params)), key=k_run,
                  update=jnp.zeros((), jnp.int32))


def _init_seeds(init_one, keys: Array) -> Runner:
    """``init_one`` for each key, stacked along a leading seed axis.

    Several seeds go through ``lax.map`` (one seed after the other), not ``vmap``: under ``vmap``
    the orthogonal initialisers become batched QR factorisations (LAPACK ``geqrf``/``orgqr``
    custom calls with a batch dimension), and jaxlib 0.10.x splits such a batch into tasks on
    XLA:CPU's intra-op thread pool and blocks a pool thread until they finish
    (``ParallelBatchMap``). When XLA runs as many of these custom calls concurrently as the pool
    has threads (the actor and critic layers are independent), every pool thread waits for tasks
    that no thread is left to run: the process hangs with the CPU idle. An
    unbatched QR runs inline, so ``lax.map`` cannot deadlock. Per seed it gives the network that
    ``vmap`` gives (the same bits) and the same environments (a two-seed run's learning curve is
    bit-identical to the ``vmap`` version's where that one finishes, pinned to one core). One
    seed keeps the ``vmap`` of size one: a batch of one is never split, and one-seed results stay
    bit-identical to earlier runs. The training chunk has no LAPACK call and stays a ``vmap``.
    """
    if keys.shape[0] == 1:
        return jax.vmap(init_one)(keys)
    return jax.lax.map(init_one, keys)


def _device_index(axis_name: str | None) -> Array:
    return jax.lax.axis_index(axis_name) if axis_name else jnp.zeros((), jnp.int32)


def _pmean(x, axis_name: str | None):
    return jax.lax.pmean(x, axis_name) if axis_name else x


class Transition(NamedTuple):
    """One environment step of the rollout, per environment (leading axes (T, E) once scanned)."""

    obs: Array  # normalised observation the policy saw
    raw_obs: Array  # observation before normalisation (for the running statistics)
    action: Array
    logp: Array  # log-probability of the action under the rollout's policy
    value: Array  # critic's value of obs
    reward: Array  # training reward: scaled, plus the discounted value of a truncated episode's last observation
    done: Array
    raw_reward: Array  # the environment's reward
    terminated: Array
    gains: Array | None  # the gains the environment applied, when it reports them


def _rollout(ppo_config: PPOConfig, env, env_params, runner: Runner, apply_fn,
             key: Array) -> tuple[Any, Array, Transition]:
    """``ppo_config.num_steps`` steps of every environment under the current policy: (env state, last observation,
    the transitions (T, E, ...))."""
    stats = runner.stats
    num_envs = runner.obs.shape[0]

    def env_step(carry, k):
        env_state, obs = carry
        k_act, k_env = jax.random.split(k)
        nobs = stats.normalize(obs)
        mean, sigma, value = apply_fn(runner.params, nobs)
        action = mean + sigma * jax.random.normal(k_act, mean.shape)
        logp = gaussian_log_prob(action, mean, sigma)
        obs2, env_state, r, done, info = jax.vmap(env.step, (0, 0, 0, None))(
            jax.random.split(k_env, num_envs), env_state, action, env_params)
        _, _, v_term = apply_fn(runner.params, stats.normalize(info["terminal_obs"]))
        r_train = ppo_config.reward_scale * r + ppo_config.gamma * v_term * info["truncated"]
        return (env_state, obs2), Transition(obs=nobs, raw_obs=obs, action=action, logp=logp, value=value,
                                             reward=r_train, done=done, raw_reward=r,
                                             terminated=info["terminated"], gains=info.get("gains"))

    (env_state, obs), traj = jax.lax.scan(env_step, (runner.env_state, runner.obs),
                                          jax.random.split(key, ppo_config.num_steps))
    return env_state, obs, traj


def _new_statistics(stats: RunningStats, raw_obs: Array, axis_name: str | None) -> RunningStats:
    """The observation statistics for the next rollout, updated with this rollout's (averaged over devices)."""
    flat_obs = raw_obs.reshape(-1, raw_obs.shape[-1])
    b_mean = _pmean(flat_obs.mean(0), axis_name)
    b_var = _pmean(((flat_obs - b_mean) ** 2).mean(0), axis_name)
    n_dev = jax.lax.psum(1, axis_name) if axis_name else 1
    return stats.update(b_mean, b_var, jnp.asarray(flat_obs.shape[0] * n_dev, stats.count.dtype))


def _learn(ppo_config: PPOConfig, apply_fn, tx, params, opt_state, batch: Batch, key: Array, axis_name: str | None):
    """``ppo_config.update_epochs`` epochs of minibatch steps on ``batch``: (params, optimiser state, loss
    statistics)."""
    n = batch.obs.shape[0]
    mb = n // ppo_config.num_minibatches
    grad_fn = jax.value_and_grad(ppo_loss, has_aux=True)

    def epoch(carry, k):
        params, opt_state = carry
        perm = jax.random.permutation(k, n)[: mb * ppo_config.num_minibatches]
        shuffled = jax.tree.map(lambda x: x[perm].reshape((ppo_config.num_minibatches, mb) + x.shape[1:]), batch)

        def minibatch(carry, b):
            params, opt_state = carry
            (loss, aux), grads = grad_fn(params, apply_fn, b, ppo_config)
            grads = _pmean(grads, axis_name)
            updates, opt_state = tx.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), aux

        return jax.lax.scan(minibatch, (params, opt_state), shuffled)

    (params, opt_state), aux = jax.lax.scan(epoch, (params, opt_state), jax.random.split(key, ppo_config.update_epochs))
    return params, opt_state, aux


def _update_seed(ppo_config: PPOConfig, env, env_params, runner: Runner, axis_name: str | None):
    """One PPO update for one seed on this device's environments: rollout, GAE, statistics, epochs."""
    net = ppo_config.network(env.action_size)
    apply_fn = actor_critic_apply(net)
    tx = make_optimizer(ppo_config)
    key, k_roll, k_perm = jax.random.split(runner.key, 3)
    dev = _device_index(axis_name)
    k_roll = jax.random.fold_in(k_roll, dev)
    k_perm = jax.random.fold_in(k_perm, dev)
    env_state, obs, traj = _rollout(ppo_config, env, env_params, runner, apply_fn, k_roll)
    _, _, last_value = apply_fn(runner.params, runner.stats.normalize(obs))
    adv, target = compute_gae(traj.reward, traj.value, traj.done, last_value, ppo_config.gamma, ppo_config.gae_lambda)
    new_stats = _new_statistics(runner.stats, traj.raw_obs, axis_name)
    batch = Batch(obs=traj.obs, action=traj.action, logp=traj.logp, value=traj.value, adv=adv, target=target)
    batch = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), batch)
    params, opt_state, aux = _learn(ppo_config, apply_fn, tx, runner.params, runner.opt_state, batch, k_perm, axis_name)
    metrics = {k: v.mean() for k, v in aux.items()}
    metrics.update({"mean_reward": traj.raw_reward.mean(), "terminated_frac": traj.terminated.mean()})
    if traj.gains is not None:
        metrics.update({f"eta{i + 1}": traj.gains[..., i].mean() for i in range(traj.gains.shape[-1])})
    metrics = _pmean(metrics, axis_name)
    new = Runner(params=params, opt_state=opt_state, env_state=env_state, obs=obs, stats=new_stats, key=key,
                 update=runner.update + 1)
    return new, metrics


def _chunk_seed(ppo_config, env, env_params, runner, axis_name):
    return jax.lax.scan(lambda r, _: _update_seed(ppo_config, env, env_params, r, axis_name), runner, None,
                        length=ppo_config.updates_per_chunk)


def _strong(tree):
    """The runner with strongly typed leaves. Leaves copied from Python-float parameters are weakly
    typed, while a runner restored from a checkpoint is not; without this, the first chunk after
    ``init`` and after a resume would each compile a second program."""
    return jax.tree.map(lambda x: jax.lax.convert_element_type(x, x.dtype), tree)


def make_train(ppo_config: PPOConfig, env_params: Any, devices: list | None = None, *, env: Any):
    """Build ``(init, train_chunk)`` for ``ppo_config`` and ``env_params`` over ``devices``.

    ``env`` is any object with gymnax-style ``reset(key, params)``, ``step(key, state, action,
    params) -> (obs, state, reward, done, info)`` (info with ``terminal_obs``, ``truncated``,
    ``terminated``), ``obs_size(params)`` and ``action_size``, e.g. ``learn.env.TrafficEnv`` (passed
    explicitly: PPO does not depend on the traffic environment).

    Every leaf of the returned ``Runner`` has a leading device axis (sharded over the mesh,
    ``P(AXIS)``) and then a seed axis; the network, optimiser state, statistics and key are
    identical across devices (kept so by ``lax.pmean``), the environments are split between
    devices. ``num_envs`` (the total) must be divisible by the number of devices.
    ``devices=None``: the most of ``jax.devices()`` (every process's devices) that ``num_envs``
    and the minibatches divide (all of them for the defaults). ``ppo_config`` and ``env_params`` are
    traced arguments.
    """
    mesh = train_mesh(ppo_config, devices)
    n_dev = mesh.size
    local_envs = ppo_config.num_envs // n_dev
    check_ppo_config(ppo_config)
    sharded, replicated_ = NamedSharding(mesh, P(AXIS)), NamedSharding(mesh, P())

    def _init(ppo_config, env_params, keys):
        runner = _init_seeds(lambda k: _init_seed(ppo_config, env, env_params, local_envs, k, _device_index(AXIS)),
                             keys)
        return jax.tree.map(lambda x: x[None], _strong(runner))  # this device's block of the device axis

    def _chunk(ppo_config, env_params, runner):
        runner = jax.tree.map(lambda x: x[0], runner)
        runner, metrics = jax.vmap(functools.partial(_chunk_seed, ppo_config, env, env_params, axis_name=AXIS))(runner)
        return jax.tree.map(lambda x: x[None], _strong(runner)), metrics

    def sharded_fn(fn, in_specs, out_specs, in_shardings, out_shardings):  # jit of the per-device body
        return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False),
                       in_shardings=in_shardings, out_shardings=out_shardings)

    s_init = sharded_fn(_init, (P(), P(), P()), P(AXIS), replicated_, sharded)
    s_chunk = sharded_fn(_chunk, (P(), P(), P(AXIS)), (P(AXIS), P()), (replicated_, replicated_, sharded),
                         (sharded, replicated_))

    def init(key: Array) -> Runner:
        return s_init(ppo_config, env_params, jax.random.split(key, ppo_config.num_seeds))

    def train_chunk(runner: Runner) -> tuple[Runner, dict]:
        """``updates_per_chunk`` updates; metrics have shape (seeds, updates_per_chunk), on this
        process's first device."""
        runner, metrics = s_chunk(ppo_config, env_params, runner)
        return runner, local_copy(metrics)

    return init, train_chunk


def train_mesh(ppo_config: PPOConfig, devices: list | None = None) -> Mesh:
    """The one-axis (``AXIS``) mesh PPO splits its environments over: ``devices``, or the most of
    ``jax.devices()`` that ``num_envs`` and the minibatches divide; ``ValueError`` if they do not."""
    if devices is None:  # every device the batch splits over (one per core by default, jaxtraffic.platform.devices)
        devices = list(jax.devices())
        k = max(k for k in range(1, len(devices) + 1) if ppo_config.num_envs % k == 0
                and ((ppo_config.num_envs // k) * ppo_config.num_steps) % ppo_config.num_minibatches == 0 or k == 1)
        devices = devices[:k]
    devices = list(devices)
    n_dev = len(devices)
    if ppo_config.num_envs % n_dev:
        raise ValueError(f"num_envs={ppo_config.num_envs} is not divisible by the {n_dev} devices")
    if ((ppo_config.num_envs // n_dev) * ppo_config.num_steps) % ppo_config.num_minibatches:
        raise ValueError("num_envs/devices * num_steps must be divisible by num_minibatches")
    return Mesh(np.array(devices), (AXIS,))
