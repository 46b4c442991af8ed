"""Gymnax-style environment for learning the paper's three-gain policy (MODEL.md section 9).

Pure functions ``reset(key, params) -> (obs, state)`` and
``step(key, state, action, params) -> (obs, state, reward, done, info)`` over ``flax.struct``
pytrees, so a batch of environments is a ``vmap`` and a batch of scenarios a ``vmap`` over params.

* Observation: [rho/rho_bar - 1, v/v_bar - 1, h_prev/h_bar - 1] on the grid, normalised by the
  nominal equilibrium (dimensionless), then the gains applied at the previous step / gain_max:
  shape (3 n + 3,).
* Action: three unbounded reals ``a``; the policy's gains are gain_max * tanh(a) (a bounded
  symmetric range, MODEL.md 9). The gains applied move a fraction ``gain_filter`` of the way from
  the previous step's gains to them (``filter_gains``; 1: applied directly, as in the paper; the
  gains start at 0, i.e. h = h_bar) and act on normalised deviations through
  ``controllers.gain_law``.
* Reward: the paper's r = -sum_i [(rho~_i/rho_bar)^2 + (v~_i/v_bar)^2] of the state after the
  step (dimensionless), minus ``accel_weight`` times the step's ``acceleration_cost`` (the
  acceleration part of the J_comfort integrand), ``h_rate_weight`` times ``h_rate_cost`` and
  ``wave_weight`` times ``backward_wave_cost`` (all 0 by default here, i.e. the paper's reward).
* Episodes last ``horizon`` steps and end by *truncation* (``info["truncated"]``: bootstrap the
  value of ``info["terminal_obs"]``). A plant that leaves the physical region *terminates* with
  reward ``-diverge_penalty``. ``step`` resets finished environments itself.
* Domain randomisation, drawn at each reset: initial amplitude (veh/m), integer wavenumber and
  phase of the cosine perturbation, and a uniform density offset (veh/m); plant delay (a multiple
  of dt) and plant alpha (uniform ranges); per-step alpha noise (``traffic.alpha_noise``).
  Metrics stay relative to the nominal equilibrium of ``traffic`` (MODEL.md section 12).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic import delay as delay_buffer
from jaxtraffic import metrics as M
from jaxtraffic.controllers import Observation, gain_law, saturate
from jaxtraffic.linear import LinearModel, gain_law_is_regular, gain_law_wave_speed, linearize
from jaxtraffic.params import TrafficParams, equilibrium
from jaxtraffic.rollout import PlantState, initial_state, paper_initial_condition, plant_step

Array = jax.Array


@struct.dataclass
class EnvParams:
    """Environment settings; ``traffic`` is the nominal plant (its delay is the training delay).

    Ranges (lo, hi) are sampled uniformly at every reset; equal bounds disable randomisation.
    """

    traffic: TrafficParams = TrafficParams(delay=4.0)
    horizon: int = 3000  # steps per episode (300 s)
    gain_max: float = 5.0  # |eta_i| <= gain_max (dimensionless)
    amp_min: float = 0.010  # veh/m
    amp_max: float = 0.010
    wavenumber_min: int = 4
    wavenumber_max: int = 4
    phase_max: float = 0.0  # rad; phase ~ U(0, phase_max)
    offset_min: float = 0.0  # veh/m; uniform density offset of the initial condition
    offset_max: float = 0.0
    delay_min: float = 4.0  # s
    delay_max: float = 4.0
    alpha_min: float = 0.15
    alpha_max: float = 0.15
    diverge_penalty: float = 100.0
    accel_weight: float = 0.0  # s^4/m^2; 0: the paper's reward
    gain_filter: float = 1.0  # in (0, 1]; 1: the policy's gains are applied directly
    h_rate_weight: float = 0.0  # dimensionless; 0: the paper's reward
    wave_weight: float = 0.0  # dimensionless; 0: the paper's reward
    wave_speed_min: float = 1.0  # m/s


@struct.dataclass
class EnvState:
    plant: PlantState
    plant_params: TrafficParams  # this episode's plant (randomised delay / alpha)
    t: Array  # step within the episode
    gains: Array  # gains applied at the previous step, shape (3,) (dimensionless)


def make_env_params(traffic: TrafficParams | None = None, **kwargs) -> EnvParams:
    """EnvParams whose delay range defaults to the plant's delay and alpha range to its alpha."""
    traffic = TrafficParams(delay=4.0) if traffic is None else traffic
    kwargs.setdefault("delay_min", float(traffic.delay))
    kwargs.setdefault("delay_max", float(traffic.delay))
    kwargs.setdefault("alpha_min", float(traffic.alpha))
    kwargs.setdefault("alpha_max", float(traffic.alpha))
    ep = EnvParams(traffic=traffic, **kwargs)
    for lo, hi in (("amp_min", "amp_max"), ("wavenumber_min", "wavenumber_max"), ("offset_min", "offset_max"),
                   ("delay_min", "delay_max"), ("alpha_min", "alpha_max")):
        if getattr(ep, lo) > getattr(ep, hi):
            raise ValueError(f"{lo}={getattr(ep, lo)} > {hi}={getattr(ep, hi)}")
    if ep.delay_max > traffic.max_delay_steps * traffic.dt + 1e-9:
        raise ValueError(f"delay_max={ep.delay_max} s exceeds the buffer ({traffic.max_delay_steps} steps)")
    if not (0.0 <= ep.alpha_min and ep.alpha_max <= 1.0):
        raise ValueError("alpha range must lie in [0, 1]")
    if not 0.0 < ep.gain_filter <= 1.0:
        raise ValueError(f"gain_filter must lie in (0, 1], got {ep.gain_filter}")
    if ep.h_rate_weight < 0.0 or ep.accel_weight < 0.0:
        raise ValueError("h_rate_weight and accel_weight must be >= 0")
    if ep.horizon < 1:
        raise ValueError(f"horizon must be >= 1 step, got {ep.horizon}")
    return ep


def obs_size(params: EnvParams) -> int:
    return 3 * params.traffic.n_points + 3


def obs_vector(rho: Array, v: Array, h_prev: Array, nominal: TrafficParams) -> Array:
    """Normalised observation [rho/rho_bar - 1, v/v_bar - 1, h_prev/h_bar - 1], shape (3 n,)."""
    rho_bar, v_bar = equilibrium(nominal)
    return jnp.concatenate([rho / rho_bar - 1.0, v / v_bar - 1.0, h_prev / nominal.h_bar - 1.0])


def policy_input(rho: Array, v: Array, h_prev: Array, gains_prev: Array, nominal: TrafficParams,
                 gain_max: Array | float) -> Array:
    """The policy's observation: ``obs_vector`` followed by gains_prev / gain_max, shape (3 n + 3,)."""
    chex.assert_shape(gains_prev, (3,))
    return jnp.concatenate([obs_vector(rho, v, h_prev, nominal), gains_prev / gain_max])


def observe(plant: PlantState, gains_prev: Array, params: EnvParams) -> Array:
    """Observation of a plant state whose last applied gains were ``gains_prev``, shape (3 n + 3,)."""
    return policy_input(plant.rho, plant.v, plant.h_prev, gains_prev, params.traffic, params.gain_max)


def action_to_gains(action: Array, params: EnvParams) -> Array:
    """The policy's gains eta = gain_max * tanh(action), shape (3,)."""
    return params.gain_max * jnp.tanh(action)


def filter_gains(gains_prev: Array, target: Array, gain_filter: Array | float) -> Array:
    """First-order filter: gains_prev + gain_filter (target - gains_prev). With gain_filter = k the
    applied gains follow the policy's with a time constant of about dt / k."""
    return gains_prev + gain_filter * (target - gains_prev)


def reset(key: Array, params: EnvParams) -> tuple[Array, EnvState]:
    """Draw an episode (initial condition, plant delay and alpha) and return (obs, state)."""
    return _reset(key, params, None)


def _reset(key: Array, params: EnvParams, sent: delay_buffer.DelayBuffer | None) -> tuple[Array, EnvState]:
    """``reset``; with ``sent`` given, its storage is reused (restarted in O(n)) instead of a new
    (capacity x n) buffer being filled, which keeps the auto-reset inside ``step`` cheap."""
    k_amp, k_wn, k_ph, k_d, k_a = jax.random.split(key, 5)
    k_off = jax.random.fold_in(key, 1)  # kept out of the split: the other draws stay as they were
    tp = params.traffic
    amp = jax.random.uniform(k_amp, minval=params.amp_min, maxval=params.amp_max)
    wn = jax.random.randint(k_wn, (), params.wavenumber_min, params.wavenumber_max + 1)
    phase = jax.random.uniform(k_ph, maxval=params.phase_max)
    offset = jax.random.uniform(k_off, minval=params.offset_min, maxval=params.offset_max)
    d_lo = jnp.round(params.delay_min / tp.dt).astype(jnp.int32)
    d_hi = jnp.round(params.delay_max / tp.dt).astype(jnp.int32)
    delay = jax.random.randint(k_d, (), d_lo, d_hi + 1) * tp.dt
    alpha = jax.random.uniform(k_a, minval=params.alpha_min, maxval=params.alpha_max)
    plant_params = tp.replace(delay=delay, alpha=alpha)
    rho0, v0 = paper_initial_condition(tp, amp, wn.astype(jnp.float32), phase, offset=offset)
    plant = initial_state(plant_params, rho0, v0) if sent is None else PlantState(
        rho=rho0, v=v0, sent=delay_buffer.restart(sent, jnp.full_like(rho0, tp.h_bar)),
        h_prev=jnp.full_like(rho0, tp.h_bar), step=jnp.zeros((), jnp.int32), diverged=jnp.zeros((), bool),
        diverged_step=jnp.full((), -1, jnp.int32))
    gains = jnp.zeros((3,), rho0.dtype)
    state = EnvState(plant=plant, plant_params=plant_params, t=jnp.zeros((), jnp.int32), gains=gains)
    return observe(plant, gains, params), state


def acceleration_cost(before: PlantState, after: PlantState, nominal: TrafficParams) -> Array:
    """sum_i (rho_i / rho_bar) a_i^2 over one step, m^2/s^4: the acceleration part of the J_comfort
    integrand (MODEL.md section 10), with a = ``metrics.material_acceleration`` (as J_comfort).

    The jerk part (a_t^2) is left out on purpose: under the Gaussian exploration noise of training
    the gains change every step, and the jerk of that noise dwarfs everything else in the reward.
    """
    rho_bar, _ = equilibrium(nominal)
    a = M.material_acceleration(before.v, after.v, nominal.dx, nominal.dt)
    return jnp.sum(before.rho / rho_bar * a * a, axis=-1)


def h_rate_cost(h_prev: Array, h: Array, h_bar: Array | float) -> Array:
    """sum_i ((h_i - h_prev_i) / h_bar)^2: how much the commanded time gap moves in one step
    (dimensionless). Unlike the acceleration, which the delay D postpones, it depends on this
    step's action alone, so its credit is immediate."""
    return jnp.sum(((h - h_prev) / h_bar) ** 2, axis=-1)


def backward_wave_cost(gains: Array, lm: LinearModel, speed_min: Array | float, scale: float = 5.0) -> Array:
    """0 when the gains' closed-loop wave speed s (``linear.gain_law_wave_speed``) is >= speed_min
    (m/s), rising linearly to 1 at speed_min - scale and beyond; 1 also where the relaxed relation
    v~ = c rho~ breaks down (its denominator <= 0, s changes sign through infinity). Dimensionless."""
    s = gain_law_wave_speed(gains, lm)
    return jnp.where(gain_law_is_regular(gains, lm), jnp.clip((speed_min - s) / scale, 0.0, 1.0), 1.0)


def step(key: Array, state: EnvState, action: Array, params: EnvParams):
    """Apply the gains ``action`` for one dt; returns (obs, state, reward, done, info).

    info: ``terminal_obs`` (observation before any reset), ``truncated`` and ``terminated``
    (bool), ``gains`` (applied, shape (3,)).
    """
    chex.assert_shape(action, (3,))
    k_plant, k_reset = jax.random.split(key)
    tp = params.traffic
    rho_bar, v_bar = equilibrium(tp)
    gains = filter_gains(state.gains, action_to_gains(action, params), params.gain_filter)
    p = state.plant
    obs_struct = Observation(rho=p.rho, v=p.v, h_prev=p.h_prev, t=p.step * tp.dt, sent=p.sent)
    h = saturate(gain_law(gains, obs_struct, tp), tp).astype(p.rho.dtype)
    plant = plant_step(p, h, state.plant_params, k_plant)
    terminated = plant.diverged
    r = (M.reward(plant.rho, plant.v, rho_bar, v_bar) - params.accel_weight * acceleration_cost(p, plant, tp)
         - params.h_rate_weight * h_rate_cost(p.h_prev, h, tp.h_bar)
         - params.wave_weight * backward_wave_cost(gains, linearize(tp), params.wave_speed_min))
    r = jnp.where(terminated, -params.diverge_penalty, r)
    t = state.t + 1
    truncated = (t >= params.horizon) & ~terminated
    done = terminated | truncated
    terminal_obs = observe(plant, gains, params)
    obs_reset, state_reset = _reset(k_reset, params, plant.sent)
    new_state = EnvState(plant=plant, plant_params=state.plant_params, t=t, gains=gains)
    new_state = jax.tree.map(lambda a, b: jnp.where(done, a, b), state_reset, new_state)
    # both branches share the buffer storage: select only its O(n) bookkeeping, never the data
    new_state = new_state.replace(plant=new_state.plant.replace(
        sent=new_state.plant.sent.replace(data=plant.sent.data)))
    obs = jnp.where(done, obs_reset, terminal_obs)
    info = {"terminal_obs": terminal_obs, "truncated": truncated, "terminated": terminated, "gains": gains}
    return obs, new_state, r, done, info


class GainEnv:
    """The traffic gain environment as an object with the gymnax-style interface that
    ``ppo.make_train`` expects: ``reset``, ``step``, ``obs_size(params)``, ``action_size``."""

    action_size = 3
    reset = staticmethod(reset)
    step = staticmethod(step)
    obs_size = staticmethod(obs_size)
