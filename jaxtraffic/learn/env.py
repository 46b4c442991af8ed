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
  The defaults of ``EnvParams`` are the training defaults (``learn.config``, ``train.py``).
* Episodes last ``horizon`` steps and end by *truncation* (``info["truncated"]``: bootstrap the
  value of ``info["terminal_obs"]``). A plant that leaves the physical region *terminates* with
  reward ``-diverge_penalty``. ``step_env`` resets finished environments itself, reusing the delay
  buffer's storage (``initial_state(..., sent=...)`` and ``select_state``: O(n), not O(capacity n)).
* Domain randomisation, drawn at each reset: initial amplitude (veh/m), integer wavenumber and
  phase of the cosine perturbation; plant delay (a multiple of dt) and plant alpha (uniform
  ranges); per-step alpha noise (``traffic.alpha_noise``). Metrics stay relative to the nominal
  equilibrium of ``traffic`` (docs/model.md section 12).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control import gain_policy as gp
from jaxtraffic.control.gain_law import FILTER_SIGMA, sigma_nodes
from jaxtraffic.learn.fields import check_fields, fail, hyper
from jaxtraffic.model.linear import LinearModel, gain_law_is_regular, gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import node_weight
from jaxtraffic.sim.plant import PlantState, closed_loop_step, initial_state, plant_alpha, select_state

Array = jax.Array


@struct.dataclass
class EnvParams:
    """Environment settings; ``traffic`` is the nominal plant (its delay is the training delay).

    Ranges (lo, hi) are sampled uniformly at every reset; equal bounds disable randomisation.
    """

    traffic: TrafficParams = TrafficParams(delay=4.0)
    horizon: int = 1000  # steps per episode (100 s)
    # |eta_i| <= gain_max_i (dimensionless): one bound for all gains or one per gain (a 3-tuple)
    gain_max: float | tuple[float, float, float] = hyper((1.0, 3.0, 3.0), lo=0.0, lo_open=True)
    amp_min: float = 0.010  # veh/m
    amp_max: float = 0.010
    wavenumber_min: int = 4
    wavenumber_max: int = 4
    phase_max: float = hyper(0.0, lo=0.0)  # rad; phase ~ U(0, phase_max)
    delay_min: float = 4.0  # s
    delay_max: float = 4.0
    alpha_min: float = 0.15
    alpha_max: float = 0.15
    diverge_penalty: float = hyper(100.0, lo=0.0)  # dimensionless, the reward of the diverging step, subtracted
    # applied gains move this fraction of the way to the policy's each step; 1: applied directly (the paper)
    gain_filter: float = hyper(0.2, lo=0.0, lo_open=True, hi=1.0)
    h_rate_weight: float = hyper(0.2, lo=0.0)  # dimensionless; 0: the paper's reward
    wave_weight: float = hyper(0.5, lo=0.0)  # dimensionless, times backward_wave_cost; 0: the paper's reward
    wave_speed_min: float = 1.0  # m/s, backward_wave_cost's threshold
    # observation: 0: the full normalised fields (3 n values); K > 0: each field averaged over K equal segments
    obs_segments: int = hyper(16, lo=0, static=True)
    # the gain law's Gaussian filter of the observed rho~, v~, in node spacings of ``traffic``'s grid
    # (``control.gain_law``; make_env_params sets it from a width in m); 0: the paper's pointwise law
    filter_nodes: float = struct.field(pytree_node=False, default=0.0)


@struct.dataclass
class EnvState:
    plant: PlantState
    plant_params: TrafficParams  # this episode's plant (randomised delay / alpha)
    t: Array  # step within the episode
    gains: Array  # gains applied at the previous step, shape (3,) (dimensionless): the controller state


def make_env_params(traffic: TrafficParams | None = None, filter_sigma: float = FILTER_SIGMA, **kwargs) -> EnvParams:
    """EnvParams whose delay range defaults to the plant's delay and alpha range to its alpha;
    ``filter_sigma``: width (m) of the gain law's spatial filter on ``traffic``'s grid (0: none)."""
    traffic = TrafficParams(delay=4.0) if traffic is None else traffic
    kwargs["filter_nodes"] = sigma_nodes(filter_sigma, float(traffic.dx))
    kwargs.setdefault("delay_min", float(traffic.delay))
    kwargs.setdefault("delay_max", float(traffic.delay))
    kwargs.setdefault("alpha_min", float(traffic.alpha))
    kwargs.setdefault("alpha_max", float(traffic.alpha))
    if np.ndim(kwargs.get("gain_max", 0.0)):  # one bound per gain: a tuple of floats (hashable, traced leaves)
        kwargs["gain_max"] = tuple(float(g) for g in np.asarray(kwargs["gain_max"], float).reshape(gp.N_GAINS))
    ep = EnvParams(traffic=traffic, **kwargs)
    for lo, hi in (("amp_min", "amp_max"), ("wavenumber_min", "wavenumber_max"),
                   ("delay_min", "delay_max"), ("alpha_min", "alpha_max")):
        if getattr(ep, lo) > getattr(ep, hi):
            raise ValueError(f"{lo}={getattr(ep, lo)} > {hi}={getattr(ep, hi)}")
    if ep.delay_max > traffic.max_delay_steps * traffic.dt + 1e-9:
        raise ValueError(f"delay_max={ep.delay_max} s exceeds the buffer ({traffic.max_delay_steps} steps)")
    if not (0.0 <= ep.alpha_min and ep.alpha_max <= 1.0):
        raise ValueError("alpha range must lie in [0, 1]")
    check_fields(ep)  # each field's range (learn.fields: gain_max, gain_filter, the reward weights, ...)
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
    return gp.policy_features(state.plant.observation(tp), state.gains, tp, params.gain_max, eq, params.obs_segments)


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
    plant_params = tp.replace(delay=delay, alpha=alpha)
    rho0, v0 = paper_initial_condition(tp, amp, wn.astype(jnp.float32), phase, rho_bar=rho_bar)
    return EnvState(plant=initial_state(plant_params, rho0, v0, sent=sent), plant_params=plant_params,
                    t=jnp.zeros((), jnp.int32), gains=jnp.zeros((gp.N_GAINS,), rho0.dtype))


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
    plant, gains, h, info = closed_loop_step(state.plant, state.gains, ctrl, state.plant_params, tp,
                                             plant_alpha(state.plant_params, k_plant), k_plant, eq)
    terminated = plant.diverged
    r = (info.reward - params.h_rate_weight * h_rate_cost(state.plant.h_prev, h, tp.h_bar, tp.dx)
         - params.wave_weight * backward_wave_cost(gains, linearize(tp), params.wave_speed_min))
    r = jnp.where(terminated, -params.diverge_penalty, r)
    t = state.t + 1
    truncated = (t >= params.horizon) & ~terminated
    done = terminated | truncated
    stepped = EnvState(plant=plant, plant_params=state.plant_params, t=t, gains=gains)
    terminal_obs = observe(stepped, params, eq)
    fresh = _new_episode(k_reset, params, eq[0], sent=plant.sent)
    obs = jnp.where(done, observe(fresh, params, eq), terminal_obs)

    def pick(a, b):
        return jax.tree.map(lambda x, y: jnp.where(done, x, y), a, b)

    new_state = EnvState(plant=select_state(done, fresh.plant, plant),
                         plant_params=pick(fresh.plant_params, stepped.plant_params),
                         t=pick(fresh.t, t), gains=pick(fresh.gains, gains))
    info = {"terminal_obs": terminal_obs, "truncated": truncated, "terminated": terminated, "gains": gains,
            "terminal_rho": plant.rho}
    return obs, new_state, r, done, info


reset = reset_env
step = step_env


class TrafficEnv:
    """The traffic gain environment as an object with the gymnax-style interface that
    ``learn.ppo.algorithm.make_train`` expects: ``reset``, ``step``, ``obs_size(params)``, ``action_size``."""

    action_size = gp.N_GAINS
    reset = staticmethod(reset_env)
    step = staticmethod(step_env)
    obs_size = staticmethod(obs_size)
