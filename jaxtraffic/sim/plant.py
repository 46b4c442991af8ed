"""The plant state and ONE closed-loop step (docs/model.md sections 3-5), shared by every loop.

``closed_loop_step`` is the single definition of a control step; ``sim.rollout.simulate``, the
learning environment (``learn.env``) and every trainer are scans of it. Order of step n
(t_n = n dt):
  1. the controller sees ``PlantState.observation`` = (rho^n, v^n, h^{n-1}, t_n, sent inputs)
     and returns h^n, saturated to [h_min, h_max] (``control.saturate``);
  2. h^n is pushed into the plant's ring buffer; the plant applies the input sent d = D/dt steps
     ago (h_bar before t = D);
  3. the plant advances with this step's alpha (``plant_alpha``: alpha + alpha_noise N(0, 1),
     clipped to [0, 1]; other readings of the noise: ``NoiseReading``);
  4. a state that leaves 0 < rho < 1/l, v >= 0 (or is not finite) is not accepted: the plant is
     flagged ``diverged`` and frozen at its last physical state. So is a step whose controller
     output is not finite (NaN/inf anywhere in h^n): the saturated field is still defined
     (``saturate`` maps NaN to h_bar) but the step is refused, with its own reason code.

``PlantState.diverged_reason`` says why a plant was frozen, as the int32 code of a
``sim.outcome.Divergence``: NONE (0, healthy), STATE (1, the state left the physical region),
CONTROL (2, the controller returned a non-finite time gap), INITIAL (3, the initial state was not
finite or not physical; only reachable with traced inputs, concrete ones are rejected),
PARAMS (4, traced parameters outside their valid range, ``model.params.params_valid``: a delay
beyond the buffer, a negative one, alpha outside [0, 1], ...; concrete ones are rejected by
``model.params.check_params``).
A controller whose traced settings are invalid (backstepping with a NaN or negative assumed delay) returns
a non-finite time gap, hence CONTROL. ``sim.outcome.check_outcome`` raises on a diverged result.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, overload

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.control.base import Controller, Observation, saturate
from jaxtraffic.model import delay as delay_buffer
from jaxtraffic.model.linear import linear_step, linearize
from jaxtraffic.model.params import TrafficParams, params_valid
from jaxtraffic.model.solver import arz_step, is_physical, local_cfl
from jaxtraffic.sim import metrics
from jaxtraffic.sim.outcome import Divergence

Array = jax.Array


@struct.dataclass
class PlantState:
    """State of one freeway: rho (veh/m), v (m/s), sent time gaps (ring buffer, s), the last
    sent field h_prev (s), the step counter and the divergence flag."""

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> PlantState: ...

    rho: Array
    v: Array
    sent: delay_buffer.DelayBuffer
    h_prev: Array
    step: Array
    diverged: Array
    diverged_step: Array  # step at which the state left the physical region (-1: never)
    diverged_reason: Array  # why (``Divergence`` code, int32; 0: healthy)

    def observation(self, p: TrafficParams) -> Observation:
        return Observation(rho=self.rho, v=self.v, h_prev=self.h_prev, t=self.step * p.dt, sent=self.sent)


def initial_state(p: TrafficParams, rho0: Array, v0: Array,
                  sent: delay_buffer.DelayBuffer | None = None) -> PlantState:
    """Plant state at t = 0 with a buffer whose history reads h_bar (no input sent yet).

    ``sent``: reuse this buffer's storage (``delay.restart``, O(n)) instead of allocating and
    filling a new (capacity x n) one; that keeps an environment's auto-reset cheap.
    An initial state outside the physical region (see ``solver.is_physical``) is flagged as
    diverged at step 0 and never advanced (``simulate`` rejects a concrete one with an error).
    """
    chex.assert_shape([rho0, v0], (p.n_points,))
    h0 = jnp.full_like(rho0, p.h_bar)
    buf = delay_buffer.init_buffer(h0, p.max_delay_steps) if sent is None else delay_buffer.restart(sent, h0)
    bad_params = ~params_valid(p)
    bad = bad_params | ~is_physical(rho0, v0, p)
    return PlantState(
        rho=rho0, v=v0, sent=buf, h_prev=h0,
        step=jnp.zeros((), jnp.int32), diverged=bad,
        diverged_step=jnp.where(bad, 0, -1).astype(jnp.int32),
        diverged_reason=jnp.where(bad_params, int(Divergence.PARAMS),
                                  jnp.where(bad, int(Divergence.INITIAL), int(Divergence.NONE))).astype(jnp.int32),
    )


def select_state(pred: Array, restarted: PlantState, state: PlantState) -> PlantState:
    """``restarted`` where ``pred`` else ``state``, for ``restarted = initial_state(..., sent=state.sent)``:
    both share the buffer storage, so only its O(n) bookkeeping is selected (``delay.select_restarted``)."""
    fields = {f: jnp.where(pred, getattr(restarted, f), getattr(state, f))
              for f in ("rho", "v", "h_prev", "step", "diverged", "diverged_step", "diverged_reason")}
    return PlantState(sent=delay_buffer.select_restarted(pred, restarted.sent, state.sent), **fields)


def plant_alpha(p: TrafficParams, key: Array) -> Array:
    """This step's plant penetration rate: clip(alpha + alpha_noise N(0,1), 0, 1)."""
    return jnp.clip(p.alpha + p.alpha_noise * jax.random.normal(key), 0.0, 1.0)


def plant_alpha_sequence(p: TrafficParams, key: Array, n_steps: int, dtype: Any = jnp.float32) -> Array:
    """The plant penetration rates of ``n_steps`` steps, shape (n_steps,), drawn at once:
    clip(alpha + alpha_noise N(0,1), 0, 1) (one vectorised draw instead of one per step)."""
    z = jax.random.normal(key, (n_steps,), dtype)
    return jnp.clip(p.alpha + p.alpha_noise * z, 0.0, 1.0).astype(dtype)


@dataclasses.dataclass(frozen=True)
class NoiseReading:
    """How the plant's alpha noise is drawn and who sees it (static; docs/model.md section 13.7).

    hold_steps: one draw is held for this many steps (1: redrawn every step, the default reading).
    per_node: an independent draw at every grid node (alpha then has shape (n,)) instead of one
        for the whole road.
    model_sees: the controller's nominal alpha is this step's plant alpha (its model follows the
        noisy plant; the target of the metrics and rewards stays the nominal one). Needs a
        road-wide alpha (not ``per_node``).
    The default ``NoiseReading()`` draws exactly what ``plant_alpha_sequence`` draws.
    """

    hold_steps: int = 1
    per_node: bool = False
    model_sees: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.hold_steps, int) or self.hold_steps < 1:
            raise ValueError(f"hold_steps must be an int >= 1, got {self.hold_steps!r}")
        if self.per_node and self.model_sees:
            raise ValueError("model_sees needs one alpha for the whole road (per_node=False)")


def noise_alpha_sequence(p: TrafficParams, key: Array, n_steps: int, reading: NoiseReading | None,
                         dtype: Any = jnp.float32) -> Array:
    """Plant alphas of ``n_steps`` steps under ``reading``: shape (n_steps,), or (n_steps, n) per
    node. Each draw z ~ N(0, 1) gives clip(alpha + alpha_noise z, 0, 1) and is held for
    ``hold_steps`` steps (steps k*hold .. (k+1)*hold - 1 share draw k). ``None`` or the default
    reading: ``plant_alpha_sequence`` itself (the same numbers)."""
    if reading is None or (reading.hold_steps == 1 and not reading.per_node):
        return plant_alpha_sequence(p, key, n_steps, dtype)
    n_draws = -(-n_steps // reading.hold_steps)
    shape = (n_draws, p.n_points) if reading.per_node else (n_draws,)
    z = jnp.repeat(jax.random.normal(key, shape, dtype), reading.hold_steps, axis=0)[:n_steps]
    return jnp.clip(p.alpha + p.alpha_noise * z, 0.0, 1.0).astype(dtype)


def plant_step(state: PlantState, h_sent: Array, p: TrafficParams, key: Array) -> PlantState:
    """Send ``h_sent`` (already saturated), apply the delayed input and advance the plant.

    The step's plant alpha is ``plant_alpha(p, key)``. A step that would leave the physical
    region is rejected: the state is frozen and flagged.
    """
    return _plant_step(state, h_sent, p, plant_alpha(p, key))[0]


@overload
def _plant_step(state: PlantState, h_sent: Array, p: TrafficParams, alpha: Array,
                target: None = None, bad_input: Array | bool = False) -> tuple[PlantState, Array, None]: ...
@overload
def _plant_step(state: PlantState, h_sent: Array, p: TrafficParams, alpha: Array,
                target: tuple[Array, Array], bad_input: Array | bool = False) -> tuple[PlantState, Array, Array]: ...
def _plant_step(state: PlantState, h_sent: Array, p: TrafficParams, alpha: Array,
                target: tuple[Array, Array] | None = None, bad_input: Array | bool = False
                ) -> tuple[PlantState, Array, Array | None]:
    """``plant_step`` with the plant alpha given. Returns (new state, applied (delayed) input,
    reward of the new state against ``target`` = (rho_bar, v_bar), or None without a target).

    With a target, the physicality check and the reward share one spatial reduction
    (``metrics.physical_reward``; NaN when the step left the physical region). ``bad_input``:
    the controller's output was not finite; the step is refused (reason ``Divergence.CONTROL``).
    """
    sent = delay_buffer.push(state.sent, h_sent)
    h_applied = delay_buffer.read(sent, p.delay_steps)
    if p.model == "linear":
        lm = linearize(p)
        u, x = h_applied - lm.h_bar, (state.rho - lm.rho_bar, state.v - lm.v_bar)
        if p.substeps == 1:
            r_t, v_t = linear_step(*x, u, lm)
        else:
            lm = lm.replace(dt=jnp.asarray(p.solver_dt))
            r_t, v_t = jax.lax.fori_loop(0, p.substeps, lambda _, y: linear_step(y[0], y[1], u, lm), x)
        rho, v = r_t + lm.rho_bar, v_t + lm.v_bar
    else:
        rho, v, _, _ = arz_step(state.rho, state.v, h_applied, p, alpha)
    if target is None:
        r_new, ok = None, is_physical(rho, v, p)
    else:
        r_new = metrics.physical_reward(rho, v, target[0], target[1], p.l, p.dx)
        ok = ~jnp.isnan(r_new)
    bad = (~ok | bad_input) & ~state.diverged
    frozen = state.diverged | bad
    reason = jnp.where(bad, jnp.where(bad_input, int(Divergence.CONTROL), int(Divergence.STATE)),
                       state.diverged_reason)
    new = PlantState(
        rho=jnp.where(frozen, state.rho, rho), v=jnp.where(frozen, state.v, v), sent=sent,
        h_prev=h_sent, step=state.step + 1, diverged=frozen,
        diverged_step=jnp.where(bad, state.step, state.diverged_step),
        diverged_reason=reason.astype(jnp.int32),
    )
    return new, h_applied, r_new


@struct.dataclass
class StepInfo:
    """What one closed-loop step reports besides the new state: the applied (delayed) input
    ``h_applied`` (s), the ``reward`` of the new state against the target (dimensionless; NaN
    where the step left the physical region) and the CFL number ``cfl`` of the step at every
    node (with the applied input and the plant's alpha). Unused fields cost nothing under jit."""

    h_applied: Array
    reward: Array
    cfl: Array


def closed_loop_step(plant: PlantState, cstate: Any, controller: Controller, plant_params: TrafficParams,
                     nominal: TrafficParams, alpha: Array, key: Array, target: tuple[Array, Array],
                     model_sees_noise: bool = False) -> tuple[PlantState, Any, Array, StepInfo]:
    """One control step: observe, act, saturate, send, advance. Returns (plant, cstate, h_sent, info).

    ``plant_params``: the true plant (its delay, alpha noise); ``nominal``: the parameters the
    controller believes in; ``alpha``: this step's plant alpha (``plant_alpha``); ``key``: the
    controller's PRNG key; ``target`` = (rho_bar, v_bar) of the nominal equilibrium (computed once
    by the caller), against which ``info.reward`` is measured. ``model_sees_noise`` (static): the
    controller is handed ``nominal`` with this step's plant alpha (``NoiseReading.model_sees``).
    """
    if model_sees_noise:
        nominal = nominal.replace(alpha=alpha)
    h, cstate = controller.act(cstate, plant.observation(plant_params), nominal, key)
    bad_input = ~jnp.all(jnp.isfinite(h))  # NaN/inf from the controller: refused, not clipped into range
    h = saturate(h, plant_params).astype(plant.rho.dtype)
    new, h_applied, r_new = _plant_step(plant, h, plant_params, alpha, target, bad_input)
    cfl = local_cfl(plant.rho, plant.v, h_applied, plant_params, alpha)
    return new, cstate, h, StepInfo(h_applied=h_applied, reward=r_new, cfl=cfl)
