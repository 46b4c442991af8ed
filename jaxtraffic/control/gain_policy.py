"""The learned gain policy as a controller, and the pieces it shares with the environment.

The policy (docs/model.md section 9) sees ``policy_features``: [rho/rho_bar - 1, v/v_bar - 1,
h_prev/h_bar - 1] on the grid (normalised by the nominal equilibrium, dimensionless), or with
``segments`` = K > 0 each of these fields averaged over K equal road segments (a pooled
observation, ``pool_segments``), followed by the gains applied at the previous step / gain_max:
shape (3 m + 3,), m = n or K (``feature_size``). Its action is three unbounded reals ``a``,
squashed to gains eta = gain_max tanh(a) (``action_to_gains``; ``gain_max`` a scalar or one
bound per gain, shape (3,)). The gains
applied move a fraction ``gain_filter`` of the way from the previous step's gains to them
(``filter_gains``; 1: applied directly, as in the paper; they start at 0, i.e. h = h_bar) and act
on normalised deviations through ``control.gain_law``.

Two controllers share this: ``gain_target_controller`` (the target gains are given, e.g. the
environment's action) and ``policy_controller`` (the target gains come from a network on the
normalised features). Both keep the applied gains as their controller state.
"""

from __future__ import annotations

import functools
from typing import Any, cast

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control.base import Controller, Observation
from jaxtraffic.control.gain_law import gain_law
from jaxtraffic.control.networks import ActorCritic, actor_critic_apply
from jaxtraffic.model.delay import DelayBuffer
from jaxtraffic.model.params import TrafficParams, equilibrium

Array = jax.Array
N_GAINS = 3
# a bound |eta_i| <= gain_max_i: one for all gains, or one per gain (a tuple, as ``EnvParams`` holds it, or an array)
GainMax = Array | float | tuple[float, ...]


def _bound(gain_max: GainMax) -> Array | float:
    """The gain bound as an operand: a per-gain tuple (as ``EnvParams`` holds it) becomes an array."""
    return jnp.asarray(gain_max) if isinstance(gain_max, (tuple, list)) else gain_max


@functools.cache
def _segment_matrix(n_points: int, segments: int) -> np.ndarray:
    """(segments, n_points) averaging matrix: row k is the mean over the grid points whose position
    x / L lies in [k / segments, (k + 1) / segments) (the outlet point joins the last segment)."""
    if not 1 <= segments <= n_points:
        raise ValueError(f"obs_segments must lie in [1, n_points={n_points}], got {segments}")
    idx = np.minimum((np.arange(n_points) * segments) // (n_points - 1), segments - 1)
    w = (idx[None, :] == np.arange(segments)[:, None]).astype(np.float32)
    return w / w.sum(axis=1, keepdims=True)


def pool_segments(fields: Array, segments: int) -> Array:
    """Each row of ``fields`` (shape (k, n)) averaged over ``segments`` equal road segments, shape
    (k, segments); ``segments`` = 0: unchanged."""
    if not segments:
        return fields
    return fields @ jnp.asarray(_segment_matrix(fields.shape[-1], segments)).T


def policy_features(obs: Observation, gains_prev: Array, nominal: TrafficParams, gain_max: GainMax,
                    eq: tuple[Array, Array] | None = None, segments: int = 0) -> Array:
    """The policy's observation vector, shape (``feature_size(n, segments)``,): [rho/rho_bar - 1,
    v/v_bar - 1, h_prev/h_bar - 1] (each pooled over ``segments`` road segments when > 0, static),
    then gains_prev / gain_max. ``eq``: (rho_bar, v_bar) of ``nominal`` if known."""
    chex.assert_shape(gains_prev, (N_GAINS,))
    rho_bar, v_bar = equilibrium(nominal) if eq is None else eq
    fields = jnp.stack([obs.rho / rho_bar - 1.0, obs.v / v_bar - 1.0, obs.h_prev / nominal.h_bar - 1.0])
    return jnp.concatenate([pool_segments(fields, segments).reshape(-1), gains_prev / _bound(gain_max)])


def feature_size(n_points: int, segments: int = 0) -> int:
    """Length of ``policy_features`` on a grid of ``n_points`` (pooled over ``segments`` if > 0)."""
    return 3 * (segments or n_points) + N_GAINS


def action_to_gains(action: Array, gain_max: GainMax) -> Array:
    """The policy's gains eta = gain_max * tanh(action), shape (3,); ``gain_max``: a scalar or one
    bound per gain."""
    return _bound(gain_max) * jnp.tanh(action)


def filter_gains(gains_prev: Array, target: Array, gain_filter: Array | float) -> Array:
    """First-order filter: gains_prev + gain_filter (target - gains_prev). With gain_filter = k the
    applied gains follow the target with a time constant of about dt / k."""
    return gains_prev + gain_filter * (target - gains_prev)


def normalize_obs(x: Array, mean: Array, var: Array) -> Array:
    """Observation normalised by running statistics, clipped to [-10, 10] (dimensionless)."""
    return jnp.clip((x - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0)


def filtered_gain_law(gains_prev: Array, target: Array, gain_filter: Array | float, obs: Observation,
                      nominal: TrafficParams, eq: tuple[Array, Array] | None = None,
                      sigma_nodes: float = 0.0) -> tuple[Array, Array]:
    """(h, applied gains): filter the gains towards ``target``, then apply the three-gain law
    (``eq``: the nominal equilibrium (rho_bar, v_bar) if known; ``sigma_nodes``: its spatial filter,
    static, in node spacings, ``control.gain_law``)."""
    gains = filter_gains(gains_prev, target, gain_filter)
    return gain_law(gains, obs, nominal, eq, sigma_nodes), gains


def zero_gains(settings: Any, obs: Observation, nominal: TrafficParams) -> Array:
    """Initial controller state of the gain controllers: no gains applied yet (h = h_bar)."""
    return jnp.zeros((N_GAINS,), obs.rho.dtype)


# ----------------------------------------------------------------------------- given target gains
@struct.dataclass
class GainTarget:
    """Target gains (shape (3,), dimensionless), the gain filter in (0, 1] and, optionally, the
    nominal equilibrium (rho_bar veh/m, v_bar m/s) the law acts about (None: computed per step)."""

    target: Array
    gain_filter: Array
    eq: tuple[Array, Array] | None = None


@functools.cache
def _target_act_fn(sigma_nodes: float):
    def act(settings: GainTarget, gains_prev, obs, nominal, key):
        return filtered_gain_law(gains_prev, settings.target, settings.gain_filter, obs, nominal, settings.eq,
                                 sigma_nodes)

    return act


def gain_target_controller(target: Array, gain_filter: Array | float = 1.0,
                           eq: tuple[Array, Array] | None = None, sigma_nodes: float = 0.0) -> Controller:
    """The filtered three-gain law towards the given ``target`` gains (the environment's action,
    squashed); its state is the gains applied at the previous step. ``eq``: the equilibrium of
    the ``nominal`` it will be called with, when the caller has computed it already;
    ``sigma_nodes``: the law's spatial filter (static, node spacings of the grid it acts on)."""
    settings = GainTarget(target=jnp.asarray(target), gain_filter=jnp.asarray(gain_filter, float), eq=eq)
    return Controller(settings=settings, act_fn=_target_act_fn(float(sigma_nodes)), init_fn=zero_gains,
                      name="gain_target")


# ----------------------------------------------------------------------------- learned policy
@struct.dataclass
class PolicySettings:
    """Traced settings of a policy controller: network parameters, observation mean/variance
    (shape (``feature_size``,)), the gain bound(s) and the gain filter (dimensionless,
    ``filter_gains``; broadcast to the bound's shape)."""

    params: Any
    obs_mean: Array
    obs_var: Array
    gain_max: Array
    gain_filter: Array


@functools.cache
def _policy_act_fn(hidden: tuple, init_sigma: float, obs_segments: int, sigma_nodes: float):
    network = ActorCritic(hidden=hidden, init_sigma=init_sigma)

    def act(settings: PolicySettings, gains_prev, obs, nominal, key):
        eq = equilibrium(nominal)  # once per step: the features and the law share it
        x = policy_features(obs, gains_prev, nominal, settings.gain_max, eq, obs_segments)
        mean, _, _ = actor_critic_apply(network)(settings.params, normalize_obs(x, settings.obs_mean, settings.obs_var))
        target = action_to_gains(mean, settings.gain_max)
        return filtered_gain_law(gains_prev, target, settings.gain_filter, obs, nominal, eq, sigma_nodes)

    return act


def policy_controller(params: Any, obs_mean: Array, obs_var: Array, gain_max: GainMax, *,
                      hidden: tuple, init_sigma: float = 0.5, gain_filter: float | Array = 1.0,
                      obs_segments: int = 0, sigma_nodes: float = 0.0) -> Controller:
    """Controller applying the policy's deterministic gains (the mean of its Gaussian, squashed,
    then filtered like in the environment) through the three-gain law; its state is the gains
    applied at the previous step (zero at the start). ``gain_max``: a scalar or one bound per
    gain (with a leading member axis for batched settings); ``obs_segments``: the observation's
    pooling (``policy_features``), as in training."""
    gain_max = jnp.asarray(gain_max, float)
    settings = PolicySettings(params=params, obs_mean=jnp.asarray(obs_mean), obs_var=jnp.asarray(obs_var),
                              gain_max=gain_max,
                              gain_filter=jnp.broadcast_to(jnp.asarray(gain_filter, float), gain_max.shape))
    act = _policy_act_fn(tuple(hidden), float(init_sigma), int(obs_segments), float(sigma_nodes))
    return Controller(settings=settings, act_fn=act, init_fn=zero_gains, name="ppo")


# ----------------------------------------------------------------------------- a policy as a function
ACTION_EPS = 1e-6  # a = +-1 would be an infinite pre-tanh action; the largest |a| used is 1 - ACTION_EPS


def normalised_to_action(a: Array) -> Array:
    """The environment's (pre-tanh) action for normalised gains ``a`` in [-1, 1]^3 (clipped): the target
    gains are gain_max * a, up to float rounding (the convention of Gymnasium-style policies)."""
    a = jnp.clip(jnp.asarray(a, jnp.float32), -1.0, 1.0)
    return jnp.arctanh(a * (1.0 - ACTION_EPS))


@struct.dataclass
class FunctionSettings:
    """Traced settings of a function policy: the gain bound(s) and the gain filter (dimensionless)."""

    gain_max: Array
    gain_filter: Array


def _host_policy(fn: Any, batched: bool):
    """``fn`` (numpy in, numpy out) called from traced code through ``jax.pure_callback``."""
    def call(x: Array) -> Array:
        def host(xn):
            xn = np.asarray(xn, np.float32)
            return np.asarray(fn(xn), np.float32).reshape(xn.shape[:-1] + (N_GAINS,))

        shape = jax.ShapeDtypeStruct(x.shape[:-1] + (N_GAINS,), jnp.float32)
        return jax.pure_callback(host, shape, x, vmap_method="broadcast_all" if batched else "sequential")

    return call


@functools.cache
def _function_act_fn(fn: Any, host: bool, batched: bool, obs_segments: int, sigma_nodes: float):
    policy = _host_policy(fn, batched) if host else fn

    def act(settings: FunctionSettings, gains_prev, obs, nominal, key):
        eq = equilibrium(nominal)
        x = policy_features(obs, gains_prev, nominal, settings.gain_max, eq, obs_segments)
        target = action_to_gains(normalised_to_action(policy(x)), settings.gain_max)
        return filtered_gain_law(gains_prev, target, settings.gain_filter, obs, nominal, eq, sigma_nodes)

    return act


def function_controller(fn: Any, gain_max: GainMax, *, gain_filter: float | Array = 1.0,
                        obs_segments: int = 0, sigma_nodes: float = 0.0, host: bool = True, batched: bool = False,
                        name: str = "function") -> Controller:
    """A policy given as a function as a controller: ``fn(obs) -> a``, from the gain environment's
    observation (``policy_features``, shape (``feature_size``,), float32) to normalised gains ``a`` in
    [-1, 1]^3, the action of the Gymnasium environment (``jaxtraffic.ecosystem``); the target gains
    gain_max * a are filtered and applied through the three-gain law every control period, exactly as
    the environment does. Its state is the gains applied at the previous step.

    ``host=True``: ``fn`` is any Python function of numpy arrays (e.g. a Stable-Baselines3 model's
    ``lambda obs: model.predict(obs, deterministic=True)[0]``), called through ``jax.pure_callback``
    (one observation per call; ``batched=True``: a batch (B, F) at once under ``vmap``, returning
    (B, 3)). ``host=False``: ``fn`` is a JAX function, traced into the rollout. ``fn`` must be hashable
    (functions are): the compiled rollout is cached per function."""
    gain_max = jnp.asarray(gain_max, float)
    settings = FunctionSettings(gain_max=gain_max,
                                gain_filter=jnp.broadcast_to(jnp.asarray(gain_filter, float), gain_max.shape))
    act = _function_act_fn(fn, bool(host), bool(batched), int(obs_segments), float(sigma_nodes))
    return Controller(settings=settings, act_fn=act, init_fn=zero_gains, name=name)


def equilibrium_gains(controller: Controller, nominal: TrafficParams, n_iter: int = 300) -> Array:
    """Gains (shape (3,), dimensionless) that a gain controller settles to while the plant sits at
    the equilibrium of ``nominal``: the fixed point of its filtered gains, iterated ``n_iter`` steps
    from zero (for a policy whose gains keep cycling there: the gains after ``n_iter`` steps). They
    set the closed loop's asymptotic behaviour (``model.linear.gain_law_wave_speed``).
    For a controller with batched settings, ``vmap`` over them."""
    rho_bar, v_bar = equilibrium(nominal)
    n = nominal.n_points
    obs = Observation(rho=jnp.full((n,), rho_bar), v=jnp.full((n,), v_bar), h_prev=jnp.full((n,), nominal.h_bar),
                      t=jnp.zeros(()), sent=cast(DelayBuffer, None))  # a gain law never reads the sent buffer

    def body(_, gains):
        return controller.act_fn(controller.settings, gains, obs, nominal, None)[1]

    return jax.lax.fori_loop(0, n_iter, body, jnp.zeros((N_GAINS,), obs.rho.dtype))
