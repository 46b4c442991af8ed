"""Gymnax-style environment for learning the paper's three-gain policy (docs/model.md section 9).

Pure functions ``reset_env(key, params) -> (obs, state)`` and
``step_env(key, state, action, params) -> (obs, state, reward, done, info)`` over ``flax.struct``
pytrees (``reset`` / ``step`` are the same functions), so a batch of environments is a ``vmap``
and a batch of scenarios a ``vmap`` over params. A step is one ``sim.plant.closed_loop_step``
under ``control.gain_policy.gain_target_controller``: the action, squashed to gains, is the
controller's target and the environment's ``gains`` (the applied, filtered gains) are its state.

* Observation: ``control.gain_policy.policy_features`` of the plant state and the applied gains,
  pooled over ``obs_segments`` road segments (0: the full fields, shape (3 n + 3,)); the deployed
  ``policy_controller`` computes the same.
* Action: three unbounded reals; target gains gain_max * tanh(action) (``action_to_gains``;
  ``gain_max`` a scalar or one bound per gain), filtered with ``gain_filter`` (``filter_gains``).
* Reward: the paper's r = -sum_i [(rho~_i/rho_bar)^2 + (v~_i/v_bar)^2] of the state after the
  step (dimensionless), minus ``h_rate_weight`` times ``h_rate_cost`` and ``wave_weight`` times
  ``backward_wave_cost`` of the applied gains (both weights 0: the paper's reward).
  The defaults of ``EnvParams`` are the training defaults (``runs.config``, ``train.py``).
* Episodes last ``horizon`` steps and end by *truncation* (``info["truncated"]``: bootstrap the
  value of ``info["terminal_obs"]``). A plant that leaves the physical region *terminates* with
  reward ``-diverge_penalty``. ``step_env`` resets finished environments itself, reusing the delay
  buffer's storage (``initial_state(..., sent=...)`` and ``select_state``: O(n), not O(capacity n)), and
  only at the steps where an episode of the batch ended (``auto_reset``, ``RESET_ONLY_WHERE_DONE``; on an
  accelerator a select of a fresh episode everywhere, ``_select_reset``, which needs no host round trip).
* Domain randomisation, drawn at each reset: initial amplitude (veh/m), integer wavenumber and
  phase of the cosine perturbation; plant delay (a multiple of dt) and plant alpha (uniform
  ranges); per-step alpha noise (``traffic.alpha_noise``). Metrics stay relative to the nominal
  equilibrium of ``traffic`` (docs/model.md section 12).
* Sensor noise (``EnvConfig.train_sensor_noise``): an episode's relative error level ~ U(lo, hi) (or its pool
  scenario's); each step's measurement is drawn once (``EnvState.noise``) and both the observation and the
  next step's gain law read it, as a deployed policy under ``control.noise.sensor_noise`` does. Off: no draws, and
  every other draw is what it was.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.compare.scenarios import EpisodePool
from jaxtraffic.control import gain_policy as gp
from jaxtraffic.control.gain_law import sigma_nodes
from jaxtraffic.control.noise import draw_factors, held_noise, measured
from jaxtraffic.fields import check_value, fail, range_of
from jaxtraffic.learn.autoreset import reset_where_done
from jaxtraffic.learn.env_config import EnvConfig
from jaxtraffic.model.linear import LinearModel, gain_law_is_regular, gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM, node_weight
from jaxtraffic.sim.plant import PlantState, closed_loop_step, initial_state, plant_alpha, select_state

Array = jax.Array

# step_env's automatic reset: True builds a fresh episode only at the steps where some environment of the batch
# finished (``auto_reset``, 1.7-2x the environment's steps/s); False builds one for every environment at every
# step and selects it where done (``_select_reset``, the earlier way). The two agree to float rounding: the fresh
# observation can differ by an ulp (XLA compiles it in another context), so a trained policy is not bit-identical
# across the switch (docs/model.md section 19.5). None (default): by backend, True on a CPU, False on an accelerator
# (the ``lax.cond`` on any-done would make a GPU wait for the host at every step; a select does not).
RESET_ONLY_WHERE_DONE: bool | None = None


def reset_only_where_done() -> bool:
    """Whether ``step_env`` resets with ``auto_reset`` (else ``_select_reset``): ``RESET_ONLY_WHERE_DONE``, or
    when it is None, whether JAX's default backend is the CPU (read when a step is traced)."""
    flag = RESET_ONLY_WHERE_DONE
    return jax.default_backend() == "cpu" if flag is None else bool(flag)


_C = EnvConfig()  # the defaults, defined there once (with each field's range and help)
PLANT = TrafficParams(delay=4.0)  # the default nominal (training) plant: the paper's road at D = 4 s


@struct.dataclass
class EnvParams:
    """Environment settings as the environment steps them (traced leaves, static shapes); ``traffic`` is the
    nominal plant (its delay is the training delay). Built from a ``learn.env_config.EnvConfig`` by
    ``env_params`` (or ``make_env_params`` field by field); the meaning, unit and range of each field are
    ``EnvConfig``'s, but for the initial amplitude: ``amp_min``/``amp_max`` in veh/m, the simulator's unit
    (``EnvConfig.amp_range`` in veh/km).

    Ranges (lo, hi) are sampled uniformly at every reset; equal bounds disable randomisation.
    """

    traffic: TrafficParams = PLANT
    horizon: int = round(_C.horizon_s / PLANT.dt)  # steps per episode
    # |eta_i| <= gain_max_i (dimensionless): one bound for all gains or one per gain (a 3-tuple)
    gain_max: float | tuple[float, float, float] = _C.gain_max
    # the initial wave's amplitude, veh/m (the simulator's unit; EnvConfig.amp_range is in veh/km)
    amp_min: float = _C.amp_range[0] / VEH_PER_KM
    amp_max: float = _C.amp_range[1] / VEH_PER_KM
    wavenumber_min: int = _C.wavenumber_range[0]
    wavenumber_max: int = _C.wavenumber_range[1]
    phase_max: float = _C.phase_max  # rad; phase ~ U(0, phase_max)
    delay_min: float = PLANT.delay  # s
    delay_max: float = PLANT.delay
    alpha_min: float = PLANT.alpha
    alpha_max: float = PLANT.alpha
    diverge_penalty: float = _C.diverge_penalty  # dimensionless, the reward of the diverging step, subtracted
    gain_filter: float = _C.gain_filter
    h_rate_weight: float = _C.h_rate_weight  # dimensionless; 0: the paper's reward
    wave_weight: float = _C.wave_weight  # dimensionless, times backward_wave_cost; 0: the paper's reward
    wave_speed_min: float = _C.wave_speed_min  # m/s, backward_wave_cost's threshold
    # observation: 0: the full normalised fields (3 n values); K > 0: each field averaged over K equal segments
    obs_segments: int = struct.field(pytree_node=False, default=_C.obs_segments)
    # the gain law's Gaussian filter of the observed rho~, v~, in node spacings of ``traffic``'s grid
    # (``control.gain_law``; make_env_params sets it from a width in m); 0: the paper's pointwise law
    filter_nodes: float = struct.field(pytree_node=False, default=0.0)
    # episodes drawn from a finite set (``EnvConfig.train_split``) instead of the ranges above; None: the ranges
    pool: EpisodePool | None = None
    # relative sensor error of an episode ~ U(noise_min, noise_max) (the pool's own levels with a pool), seen by the
    # policy and its law alike (``EnvState.noise``); ``sensor_noise`` (static) False: none (no draws at all)
    noise_min: float = 0.0
    noise_max: float = 0.0
    sensor_noise: bool = struct.field(pytree_node=False, default=False)


@struct.dataclass
class EnvState:
    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> EnvState: ...

    plant: PlantState
    plant_params: TrafficParams  # this episode's plant (randomised delay / alpha)
    t: Array  # step within the episode
    gains: Array  # gains applied at the previous step, shape (3,) (dimensionless): the controller state
    # with sensor noise (``EnvParams.sensor_noise``; else None): the episode's level (dimensionless) and the factors
    # (1 + level e) of the current measurement, shape (2, n): ``observe`` and the next step's law both read them
    noise_level: Array | None = None
    noise: Array | None = None


def env_params(config: EnvConfig, traffic: TrafficParams) -> EnvParams:
    """The environment of ``config`` around the nominal plant ``traffic``: episodes of ``horizon_s`` in whole
    steps, training delays D +- ``delay_spread`` (or ``delay_range``; clipped at 0, rounded to whole steps),
    alphas ``alpha_range`` (default: the plant's alone)."""
    d_lo, d_hi = config.delay_range or (max(0.0, traffic.delay - config.delay_spread),
                                        traffic.delay + config.delay_spread)
    d_lo, d_hi = (round(d / traffic.dt) * traffic.dt for d in (d_lo, d_hi))
    a_lo, a_hi = config.alpha_range or (traffic.alpha, traffic.alpha)
    return make_env_params(
        traffic, horizon=max(1, round(config.horizon_s / traffic.dt)), gain_max=config.gain_max,
        amp_min=config.amp_range[0] / VEH_PER_KM, amp_max=config.amp_range[1] / VEH_PER_KM,
        wavenumber_min=int(config.wavenumber_range[0]), wavenumber_max=int(config.wavenumber_range[1]),
        phase_max=config.phase_max, delay_min=d_lo, delay_max=d_hi,
        alpha_min=a_lo, alpha_max=a_hi, gain_filter=config.gain_filter, h_rate_weight=config.h_rate_weight,
        wave_weight=config.wave_weight, wave_speed_min=config.wave_speed_min, obs_segments=config.obs_segments,
        diverge_penalty=config.diverge_penalty, filter_sigma=config.filter_sigma,
        noise_min=config.train_sensor_noise[0], noise_max=config.train_sensor_noise[1],
        sensor_noise=config.train_sensor_noise[1] > 0,
        pool=EpisodePool.train_split(config.train_split, traffic, config.train_sensor_noise)
        if config.train_split else None)


def make_env_params(traffic: TrafficParams | None = None, filter_sigma: float = _C.filter_sigma,
                    **kwargs) -> EnvParams:
    """EnvParams field by field (the rest their defaults), whose delay range defaults to the plant's delay and
    alpha range to its alpha; ``filter_sigma``: width (m) of the gain law's spatial filter on ``traffic``'s grid
    (0: none). Each field shared with ``EnvConfig`` is checked against its range there."""
    traffic = PLANT if traffic is None else traffic
    kwargs["filter_nodes"] = sigma_nodes(filter_sigma, float(traffic.dx))
    kwargs.setdefault("delay_min", float(traffic.delay))
    kwargs.setdefault("delay_max", float(traffic.delay))
    kwargs.setdefault("alpha_min", float(traffic.alpha))
    kwargs.setdefault("alpha_max", float(traffic.alpha))
    kwargs.setdefault("sensor_noise", kwargs.get("noise_max", 0.0) > 0)  # (a pool's levels: say sensor_noise=True)
    if np.ndim(kwargs.get("gain_max", 0.0)):  # one bound per gain: a tuple of floats (hashable, traced leaves)
        kwargs["gain_max"] = tuple(float(g) for g in np.asarray(kwargs["gain_max"], float).reshape(gp.N_GAINS))
    ep = EnvParams(traffic=traffic, **kwargs)
    for lo, hi in (("amp_min", "amp_max"), ("wavenumber_min", "wavenumber_max"),
                   ("delay_min", "delay_max"), ("alpha_min", "alpha_max"), ("noise_min", "noise_max")):
        if getattr(ep, lo) > getattr(ep, hi):
            raise ValueError(f"{lo}={getattr(ep, lo)} > {hi}={getattr(ep, hi)}")
    if ep.delay_max > traffic.max_delay_steps * traffic.dt + 1e-9:
        raise ValueError(f"delay_max={ep.delay_max} s exceeds the buffer ({traffic.max_delay_steps} steps)")
    if not (0.0 <= ep.alpha_min and ep.alpha_max <= 1.0):
        raise ValueError("alpha range must lie in [0, 1]")
    if not (0.0 <= ep.noise_min and ep.noise_max <= 1.0):
        raise ValueError("sensor noise range must lie in [0, 1]")
    for f in dataclasses.fields(EnvConfig):  # each field's range (EnvConfig's: gain_max, gain_filter, ...)
        if hasattr(ep, f.name):
            check_value(f.name, getattr(ep, f.name), f.metadata.get("range"))
    check_value("filter_sigma", filter_sigma, range_of(EnvConfig, "filter_sigma"))
    if ep.obs_segments > traffic.n_points:
        raise fail("obs_segments", ep.obs_segments, f"must lie in [0, n_points = {traffic.n_points}]")
    if ep.horizon < 1:
        raise ValueError(f"horizon must be >= 1 step, got {ep.horizon}")
    return ep


def obs_size(params: EnvParams) -> int:
    return gp.feature_size(params.traffic.n_points, params.obs_segments)


def observe(state: EnvState, params: EnvParams, eq: tuple[Array, Array] | None = None) -> Array:
    """The policy's observation of ``state`` (``policy_features``), shape (``obs_size``,)."""
    tp = params.traffic
    obs = state.plant.observation(tp)
    obs = obs if state.noise is None else measured(obs, state.noise)
    return gp.policy_features(obs, state.gains, tp, params.gain_max, eq, params.obs_segments)


def action_to_gains(action: Array, params: EnvParams) -> Array:
    """The target gains of an action, gain_max * tanh(action), shape (3,)."""
    return gp.action_to_gains(action, params.gain_max)


def h_rate_cost(h_prev: Array, h: Array, h_bar: Array | float, dx: Array | float) -> Array:
    """(dx / 5 m) sum_i ((h_i - h_prev_i) / h_bar)^2: how much the commanded time gap moves in one
    step (dimensionless; weighted per node like the reward, ``metrics.node_weight``). Unlike the
    acceleration, which the delay D postpones, it depends on this step's action alone, so its credit
    is immediate."""
    return jnp.sum(((h - h_prev) / h_bar) ** 2, axis=-1) * node_weight(dx)


def backward_wave_cost(gains: Array, lm: LinearModel, speed_min: Array | float, scale: float = 5.0) -> Array:
    """0 when the gains' closed-loop wave speed s (``model.linear.gain_law_wave_speed``) is >= speed_min
    (m/s), rising linearly to 1 at speed_min - scale and beyond; 1 also where the relaxed relation
    v~ = c rho~ breaks down (its denominator <= 0, s changes sign through infinity). Dimensionless.
    The stop rule's ``min_wave_speed`` asks the same of the gains a policy settles to; this charges
    it on the applied gains at every step, so the policy learns it instead of stumbling on it."""
    s = gain_law_wave_speed(gains, lm)
    return jnp.where(gain_law_is_regular(gains, lm), jnp.clip((speed_min - s) / scale, 0.0, 1.0), 1.0)


def _new_episode(key: Array, params: EnvParams, rho_bar: Array,
                 sent=None) -> EnvState:
    """Draw an episode (initial condition, plant delay and alpha); ``sent``: a delay buffer whose
    storage the new plant state reuses (``initial_state``)."""
    k_amp, k_wn, k_ph, k_d, k_a = jax.random.split(key, 5)
    tp = params.traffic
    amp = jax.random.uniform(k_amp, minval=params.amp_min, maxval=params.amp_max)
    wn = jax.random.randint(k_wn, (), params.wavenumber_min, params.wavenumber_max + 1)
    phase = jax.random.uniform(k_ph, maxval=params.phase_max)
    d_lo = jnp.round(params.delay_min / tp.dt).astype(jnp.int32)
    d_hi = jnp.round(params.delay_max / tp.dt).astype(jnp.int32)
    delay = jax.random.randint(k_d, (), d_lo, d_hi + 1) * tp.dt
    alpha = jax.random.uniform(k_a, minval=params.alpha_min, maxval=params.alpha_max)
    rho0, v0 = paper_initial_condition(tp, amp, wn.astype(jnp.float32), phase, rho_bar=rho_bar)
    pool, i = params.pool, None
    if pool is not None:  # one scenario of the finite set (the ranges' draws above unused)
        i = jax.random.randint(k_amp, (), 0, pool.delay.shape[0])
        delay, alpha, rho0, v0 = (x[i].astype(rho0.dtype) for x in (pool.delay, pool.alpha, pool.rho0, pool.v0))
    plant_params = tp.replace(delay=delay, alpha=alpha)
    noise = {}
    if params.sensor_noise:  # the episode's level (with a pool: its scenario's) and its first measurement's error
        # a child of ``key`` the split above does not produce (fold_in(key, i) is split(key, 5)[i] for i < 5)
        k_level, k_e = jax.random.split(jax.random.fold_in(key, 5))
        level = (jax.random.uniform(k_level, minval=params.noise_min, maxval=params.noise_max) if pool is None
                 else pool.noise[i])
        noise = {"noise_level": level, "noise": draw_factors(k_e, level, rho0.shape, rho0.dtype)}
    return EnvState(plant=initial_state(plant_params, rho0, v0, sent=sent), plant_params=plant_params,
                    t=jnp.zeros((), jnp.int32), gains=jnp.zeros((gp.N_GAINS,), rho0.dtype), **noise)


def reset_env(key: Array, params: EnvParams) -> tuple[Array, EnvState]:
    """Draw an episode (initial condition, plant delay and alpha) and return (obs, state)."""
    eq = equilibrium(params.traffic)
    state = _new_episode(key, params, eq[0])
    return observe(state, params, eq), state


def step_env(key: Array, state: EnvState, action: Array, params: EnvParams):
    """Apply the gains ``action`` for one dt; returns (obs, state, reward, done, info).

    info: ``terminal_obs`` (observation before any reset), ``truncated`` and ``terminated``
    (bool), ``gains`` (applied, shape (3,)), ``terminal_rho`` (the density before any reset, veh/m,
    shape (n,): what a rendering draws).
    """
    chex.assert_shape(action, (gp.N_GAINS,))
    k_plant, k_reset = jax.random.split(key)
    tp = params.traffic
    eq = equilibrium(tp)  # once per step: the law, the reward target, both observations, the reset
    ctrl = gp.gain_target_controller(action_to_gains(action, params), params.gain_filter, eq, params.filter_nodes)
    ctrl = ctrl if state.noise is None else held_noise(ctrl, state.noise)  # the measurement the policy observed
    plant, gains, h, step_info = closed_loop_step(state.plant, state.gains, ctrl, state.plant_params, tp,
                                                  plant_alpha(state.plant_params, k_plant), k_plant, eq)
    terminated = plant.diverged
    r = (step_info.reward - params.h_rate_weight * h_rate_cost(state.plant.h_prev, h, tp.h_bar, tp.dx)
         - params.wave_weight * backward_wave_cost(gains, linearize(tp), params.wave_speed_min))
    r = jnp.where(terminated, -params.diverge_penalty, r)
    t = state.t + 1
    truncated = (t >= params.horizon) & ~terminated
    done = terminated | truncated
    level = state.noise_level
    noise = None if level is None else draw_factors(  # a child of ``key`` besides k_plant and k_reset
        jax.random.fold_in(key, 2), level, plant.rho.shape, plant.rho.dtype)
    stepped = EnvState(plant=plant, plant_params=state.plant_params, t=t, gains=gains,
                       noise_level=state.noise_level, noise=noise)
    terminal_obs = observe(stepped, params, eq)
    reset_fn = auto_reset if reset_only_where_done() else _select_reset
    obs, new_state = reset_fn(done, k_reset, stepped, terminal_obs, params, eq)
    info = {"terminal_obs": terminal_obs, "truncated": truncated, "terminated": terminated, "gains": gains,
            "terminal_rho": plant.rho}
    return obs, new_state, r, done, info


def _select_reset(done: Array, key: Array, state: EnvState, obs: Array, params: EnvParams,
                  eq: tuple[Array, Array]) -> tuple[Array, EnvState]:
    """(obs, state) of one environment, replaced by a fresh episode drawn from ``key`` where ``done``
    (a select: the fresh episode is built either way; its plant reuses the delay buffer's storage)."""
    fresh = _new_episode(key, params, eq[0], sent=state.plant.sent)
    obs = jnp.where(done, observe(fresh, params, eq), obs)

    def pick(a, b):
        return jax.tree.map(lambda x, y: jnp.where(done, x, y), a, b)

    return obs, EnvState(plant=select_state(done, fresh.plant, state.plant),
                         plant_params=pick(fresh.plant_params, state.plant_params),
                         t=pick(fresh.t, state.t), gains=pick(fresh.gains, state.gains),
                         noise_level=pick(fresh.noise_level, state.noise_level), noise=pick(fresh.noise, state.noise))


def auto_reset(done: Array, key: Array, state: EnvState, obs: Array, params: EnvParams,
               eq: tuple[Array, Array]) -> tuple[Array, EnvState]:
    """``step_env``'s automatic reset: (obs, state) with a fresh episode (drawn from ``key``) where ``done``.

    The same values, to float rounding (an ulp in the fresh observation), as a select of a fresh episode
    everywhere (``_select_reset``), but the episode is only built when some environment of the batch
    finished: under ``vmap`` (any nesting, e.g. seeds x environments) the environments of all batch levels
    are flattened into one batch and a ``lax.cond`` on any-done skips the reset at the steps where none
    finished (most steps: episodes last ``horizon``). With batched ``params`` (a ``vmap`` over scenarios)
    it falls back to the select."""
    return reset_where_done(_select_reset, done, key, state, obs, params, eq)


reset = reset_env
step = step_env


class TrafficEnv:
    """The traffic gain environment as an object with the gymnax-style interface that
    ``learn.ppo.algorithm.make_train`` expects: ``reset``, ``step``, ``obs_size(params)``, ``action_size``."""

    action_size = gp.N_GAINS
    reset = staticmethod(reset_env)
    step = staticmethod(step_env)
    obs_size = staticmethod(obs_size)
