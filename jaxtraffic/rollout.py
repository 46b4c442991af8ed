"""Batched closed-loop rollouts in ``lax.scan`` (MODEL.md sections 4, 5, 10).

``simulate`` runs one environment; ``simulate_batch`` vmaps it over a batch of parameters,
initial states, keys and (optionally) controller settings. Both are jit-compiled; the number of
steps and the recording stride are static, every physical constant, delay and gain is traced.

Order of one step n (t_n = n dt):
  1. the controller sees Observation(rho^n, v^n, h^{n-1}, t_n, sent inputs) and returns h^n,
     saturated to [h_min, h_max];
  2. h^n is pushed into the plant's ring buffer; the plant applies the input sent d = D/dt steps
     ago (h_bar before t = D);
  3. the plant advances with alpha_n = clip(alpha + alpha_noise N(0, 1), 0, 1) (the N(0, 1)
     of all steps are drawn at once, before the loop, from the plant's key);
  4. metrics accumulate; a state that leaves 0 < rho < 1/l, v >= 0 (or is not finite) is not
     accepted: the environment is flagged ``diverged`` and frozen at its last physical state.
"""

from __future__ import annotations

import functools
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic import delay as delay_buffer
from jaxtraffic import metrics as M
from jaxtraffic.controllers import Controller, Observation, open_loop, saturate
from jaxtraffic.linear import linear_step, linearize
from jaxtraffic.params import TrafficParams, equilibrium
from jaxtraffic.solver import arz_step, is_physical, local_cfl

Array = jax.Array


@struct.dataclass
class PlantState:
    """State of one freeway: rho (veh/m), v (m/s), sent time gaps (ring buffer, s), the last
    sent field h_prev (s), the step counter and the divergence flag."""

    rho: Array
    v: Array
    sent: delay_buffer.DelayBuffer
    h_prev: Array
    step: Array
    diverged: Array
    diverged_step: Array  # step at which the state left the physical region (-1: never)

    def observation(self, p: TrafficParams) -> Observation:
        return Observation(rho=self.rho, v=self.v, h_prev=self.h_prev, t=self.step * p.dt, sent=self.sent)


@struct.dataclass
class Trajectory:
    """Every ``record_every``-th step from t = 0: t (s), rho (veh/m), v (m/s), h (sent, s),
    reward, rho_L2 (veh/m) and v_L2 (m/s)."""

    t: Array
    rho: Array
    v: Array
    h: Array
    reward: Array
    rho_L2: Array
    v_L2: Array


@struct.dataclass
class SimResult:
    """Outcome of a rollout: scalar ``metrics`` (see ``finalize_metrics``), the final state,
    the final controller state and the trajectory (None unless ``record_every`` > 0)."""

    metrics: dict
    final: PlantState
    controller_state: Any
    trajectory: Trajectory | None


def paper_initial_condition(
    p: TrafficParams, amplitude: float | Array = 0.010, wavenumber: float | Array = 4.0,
    phase: float | Array = 0.0, dtype: Any = jnp.float32, offset: float | Array = 0.0,
) -> tuple[Array, Array]:
    """Initial state of MODEL.md section 5 (shapes (n_points,)).

    rho(x, 0) = rho_bar + offset + amplitude cos(2 pi wavenumber x / L + phase) (offset and
    amplitude in veh/m; the paper's: no offset, 10 veh/km, wavenumber 4), v(x, 0) = q_in / rho(x, 0).
    """
    rho_bar, _ = equilibrium(p)
    x = p.x()
    rho0 = rho_bar + offset + amplitude * jnp.cos(2.0 * jnp.pi * wavenumber * x / p.L + phase)
    rho0 = rho0.astype(dtype)
    return rho0, (p.q_in / rho0).astype(dtype)


def equilibrium_state(p: TrafficParams, dtype: Any = jnp.float32) -> tuple[Array, Array]:
    """The uniform equilibrium fields (rho_bar, v_bar), shapes (n_points,)."""
    rho_bar, v_bar = equilibrium(p)
    return jnp.full((p.n_points,), rho_bar, dtype), jnp.full((p.n_points,), v_bar, dtype)


def initial_state(p: TrafficParams, rho0: Array, v0: Array) -> PlantState:
    """Plant state at t = 0 with the buffer filled with h_bar (no input sent yet).

    An initial state outside the physical region (see ``solver.is_physical``) is flagged as
    diverged at step 0 and never advanced (``simulate`` rejects a concrete one with an error).
    """
    chex.assert_shape([rho0, v0], (p.n_points,))
    h0 = jnp.full_like(rho0, p.h_bar)
    bad = ~is_physical(rho0, v0, p)
    return PlantState(
        rho=rho0, v=v0, sent=delay_buffer.init_buffer(h0, p.max_delay_steps), h_prev=h0,
        step=jnp.zeros((), jnp.int32), diverged=bad,
        diverged_step=jnp.where(bad, 0, -1).astype(jnp.int32),
    )


def plant_alpha(p: TrafficParams, key: Array) -> Array:
    """This step's plant penetration rate: clip(alpha + alpha_noise N(0,1), 0, 1)."""
    return jnp.clip(p.alpha + p.alpha_noise * jax.random.normal(key), 0.0, 1.0)


def plant_alpha_sequence(p: TrafficParams, key: Array, n_steps: int, dtype: Any = jnp.float32) -> Array:
    """The plant penetration rates of ``n_steps`` steps, shape (n_steps,), drawn at once:
    clip(alpha + alpha_noise N(0,1), 0, 1) (one vectorised draw instead of one per step)."""
    z = jax.random.normal(key, (n_steps,), dtype)
    return jnp.clip(p.alpha + p.alpha_noise * z, 0.0, 1.0).astype(dtype)


def plant_step(state: PlantState, h_sent: Array, p: TrafficParams, key: Array) -> PlantState:
    """Send ``h_sent`` (already saturated), apply the delayed input and advance the plant.

    The step's plant alpha is ``plant_alpha(p, key)``. A step that would leave the physical
    region is rejected: the state is frozen and flagged.
    """
    return _plant_step(state, h_sent, p, plant_alpha(p, key))[0]


def _plant_step(state: PlantState, h_sent: Array, p: TrafficParams, alpha: Array,
                target: tuple[Array, Array] | None = None) -> tuple[PlantState, Array, Array | None]:
    """``plant_step`` with the plant alpha given. Returns (new state, applied (delayed) input,
    reward of the new state against ``target`` = (rho_bar, v_bar), or None without a target).

    With a target, the physicality check and the reward share one spatial reduction
    (``metrics.physical_reward``; NaN when the step left the physical region).
    """
    sent = delay_buffer.push(state.sent, h_sent)
    h_applied = delay_buffer.read(sent, p.delay_steps)
    if p.model == "linear":
        lm = linearize(p)
        r_t, v_t = linear_step(state.rho - lm.rho_bar, state.v - lm.v_bar, h_applied - lm.h_bar, lm)
        rho, v = r_t + lm.rho_bar, v_t + lm.v_bar
    else:
        rho, v, _, _ = arz_step(state.rho, state.v, h_applied, p, alpha)
    if target is None:
        r_new, ok = None, is_physical(rho, v, p)
    else:
        r_new = M.physical_reward(rho, v, target[0], target[1], p.l)
        ok = ~jnp.isnan(r_new)
    bad = ~ok & ~state.diverged
    frozen = state.diverged | bad
    new = PlantState(
        rho=jnp.where(frozen, state.rho, rho), v=jnp.where(frozen, state.v, v), sent=sent,
        h_prev=h_sent, step=state.step + 1, diverged=frozen,
        diverged_step=jnp.where(bad, state.step, state.diverged_step),
    )
    return new, h_applied, r_new


def finalize_metrics(acc: M.MetricsAccumulator, final: PlantState, target: TrafficParams,
                     n_steps: int, dx: Array | float | None = None) -> dict:
    """Scalar results of a rollout (``dx``: the plant's grid spacing, default ``target.dx``).

    J_TTT, J_fuel, J_comfort (rho in veh/km; see ``metrics``), final_rho_L2 (veh/m),
    final_v_L2 (m/s), final_reward, time_to_reward_target_s (time after which the reward stays
    >= -0.1; inf if it never does), diverged, diverged_at_s (inf if never), control_effort
    (RMS over space and time of h_sent - h_bar, s), max_cfl (largest CFL number of the steps
    taken, with the applied input and the plant's alpha).
    """
    dx = target.dx if dx is None else dx
    rho_bar, v_bar = equilibrium(target)
    dt = target.dt
    healthy_to_end = ~final.diverged
    r_final = M.reward(final.rho, final.v, rho_bar, v_bar)
    reached = healthy_to_end & (acc.last_bad_step < n_steps - 1) & (r_final >= M.REWARD_TARGET)
    tot = M.totals(acc, dx)
    return {
        "J_TTT": tot["J_TTT"],
        "J_fuel": tot["J_fuel"],
        "J_comfort": tot["J_comfort"],
        "final_rho_L2": M.l2_deviation(final.rho, rho_bar),
        "final_v_L2": M.l2_deviation(final.v, v_bar),
        "final_reward": r_final,
        "time_to_reward_target_s": jnp.where(reached, (acc.last_bad_step + 1) * dt, jnp.inf),
        "diverged": final.diverged,
        "diverged_at_s": jnp.where(final.diverged, final.diverged_step * dt, jnp.inf),
        "control_effort": tot["control_effort"],
        "max_cfl": tot["max_cfl"],
    }


def _simulate(params: TrafficParams, controller: Controller | None, rho0: Array | None,
              v0: Array | None, key: Array | None, nominal: TrafficParams | None,
              n_steps: int, record_every: int) -> SimResult:
    p = params
    nominal = p if nominal is None else nominal
    controller = open_loop() if controller is None else controller
    if rho0 is None:
        rho0, v0 = paper_initial_condition(p)
    key = jax.random.PRNGKey(0) if key is None else key
    k_plant, k_ctrl = jax.random.split(key)
    rho_bar, v_bar = equilibrium(nominal)
    state = initial_state(p, rho0, v0)
    cstate = controller.init(state.observation(p), nominal)
    acc = M.init_metrics(p.n_points, rho0.dtype)
    # rewards are tracked for the state after each step (sharing the physicality reduction);
    # the initial state's is counted here
    r0 = M.reward(rho0, v0, rho_bar, v_bar)
    acc = acc.replace(last_bad_step=jnp.where(r0 < M.REWARD_TARGET, 0, -1).astype(jnp.int32))
    # the plant's alpha of every step, drawn at once (cheaper than a draw inside the loop)
    alphas = plant_alpha_sequence(p, k_plant, n_steps, rho0.dtype)

    def one_step(carry, alpha_n):
        state, cstate, acc = carry
        n = state.step
        h, cstate = controller.act(cstate, state.observation(p), nominal, jax.random.fold_in(k_ctrl, n))
        h = saturate(h, p).astype(state.rho.dtype)
        new, h_applied, r_next = _plant_step(state, h, p, alpha_n, (rho_bar, v_bar))
        active = ~new.diverged
        cfl = local_cfl(state.rho, state.v, h_applied, p, alpha_n)
        acc = M.update_metrics(acc, step=n, rho=state.rho, v=state.v, v_next=new.v, h_sent=h,
                               rho_bar=rho_bar, v_bar=v_bar, h_bar=nominal.h_bar, dx=p.dx, dt=p.dt,
                               cfl=cfl, active=active, reward_next=r_next)
        return (new, cstate, acc), h

    carry = (state, cstate, acc)
    traj = None
    if record_every:
        if n_steps % record_every:
            raise ValueError(f"n_steps={n_steps} is not a multiple of record_every={record_every}")

        def chunk(carry, alpha_chunk):
            s = carry[0]
            carry, hs = jax.lax.scan(one_step, carry, alpha_chunk)
            rec = (s.step * p.dt, s.rho, s.v, hs[0], M.reward(s.rho, s.v, rho_bar, v_bar),
                   M.l2_deviation(s.rho, rho_bar), M.l2_deviation(s.v, v_bar))
            return carry, rec

        carry, rec = jax.lax.scan(chunk, carry, alphas.reshape(n_steps // record_every, record_every))
        traj = Trajectory(*rec)
    else:
        carry, _ = jax.lax.scan(lambda c, x: (one_step(c, x)[0], None), carry, alphas)
    state, cstate, acc = carry
    return SimResult(metrics=finalize_metrics(acc, state, nominal, n_steps, p.dx), final=state,
                     controller_state=cstate, trajectory=traj)


_simulate_jit = jax.jit(_simulate, static_argnames=("n_steps", "record_every"))


def _check_initial_condition(params: TrafficParams, rho0: Array | None, v0: Array | None) -> None:
    """Raise ``ValueError`` if a concrete initial state (single, or batched (B, n)) is not finite
    or outside 0 < rho < 1/l, v >= 0. Traced inputs are not checked (the rollout then flags
    such an environment as diverged at step 0)."""
    if rho0 is None or any(isinstance(x, jax.core.Tracer) for x in (rho0, v0, params.l)):
        return
    r, v = np.asarray(rho0, np.float64), np.asarray(v0, np.float64)
    if r.shape[-1] != params.n_points or v.shape[-1] != params.n_points:
        raise ValueError(f"rho0 and v0 need {params.n_points} points, got shapes {r.shape}, {v.shape}")
    l = np.asarray(params.l, np.float64)
    if l.ndim == 1:  # batched parameters
        l = l[:, None]
    ok = np.all((r > 0) & (r < 1.0 / l) & (v >= 0) & np.isfinite(v), axis=-1)
    if not np.all(ok):
        which = "" if np.ndim(ok) == 0 else f" in environment(s) {np.flatnonzero(~ok).tolist()}"
        raise ValueError("initial state outside the physical region (finite, 0 < rho < 1/l, v >= 0)" + which)


def simulate(
    params: TrafficParams, controller: Controller | None = None, *, n_steps: int,
    rho0: Array | None = None, v0: Array | None = None, key: Array | None = None,
    nominal: TrafficParams | None = None, record_every: int = 0,
) -> SimResult:
    """Closed-loop rollout of one freeway for ``n_steps`` steps of ``params.dt``.

    Args:
        params: the plant (its alpha, alpha_noise and delay are the true ones).
        controller: a ``Controller`` (default: open loop).
        n_steps: number of steps (static).
        rho0, v0: initial fields, shape (n_points,) (default: the paper's initial condition).
        key: PRNG key for alpha noise and stochastic controllers (default PRNGKey(0)).
        nominal: the parameters the controller and the metrics use as model and target
            (default: ``params``). MODEL.md section 12: keep the nominal target when the plant's
            alpha differs.
        record_every: record the fields every k-th step (0: no trajectory, metrics only).
    """
    if (rho0 is None) != (v0 is None):
        raise ValueError("give both rho0 and v0, or neither")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    _check_initial_condition(params, rho0, v0)
    return _simulate_jit(params, controller, rho0, v0, key, nominal, n_steps, record_every)


def simulate_batch(
    params: TrafficParams, controller: Controller | None = None, *, n_steps: int,
    rho0: Array | None = None, v0: Array | None = None, keys: Array | None = None,
    nominal: TrafficParams | None = None, record_every: int = 0, batch_controller: bool = False,
    chunk_size: int | None = 64,
) -> SimResult:
    """``simulate`` vmapped over a batch; every returned leaf gets a leading batch axis.

    Batched inputs are recognised by shape: ``params`` whose float leaves have one axis (build
    them with ``stack_params``), ``rho0``/``v0`` of shape (B, n_points), ``keys`` of shape (B, 2).
    The controller is batched only when ``batch_controller`` is set (its settings then carry
    a leading batch axis). ``nominal`` is shared (not batched). At least one input must be batched.

    ``chunk_size`` (static): a batch larger than this runs as a sequential loop over chunks of
    ``chunk_size`` environments, each chunk vmapped over the whole rollout, so that the working
    set of a chunk stays in cache (on a CPU this is 1.5-3x faster for large batches than one
    vmap over everything). ``None`` or 0: a single vmap. Results do not depend on it beyond
    rounding, and every environment stays independent of the others.
    """
    p_axis = 0 if jnp.ndim(jax.tree_util.tree_leaves(params)[0]) == 1 else None
    r_axis = 0 if rho0 is not None and jnp.ndim(rho0) == 2 else None
    k_axis = 0 if keys is not None and jnp.ndim(keys) == 2 else None
    c_axis = 0 if batch_controller else None
    if (p_axis, r_axis, k_axis, c_axis) == (None,) * 4:
        raise ValueError("simulate_batch: nothing is batched; use simulate")
    if (rho0 is None) != (v0 is None):
        raise ValueError("give both rho0 and v0, or neither")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    _check_initial_condition(params, rho0, v0)
    return _simulate_batch_jit(params, controller, rho0, v0, keys, nominal, n_steps, record_every,
                               (p_axis, c_axis, r_axis, r_axis, k_axis), chunk_size or 0)


@functools.partial(jax.jit, static_argnames=("n_steps", "record_every", "axes", "chunk_size"))
def _simulate_batch_jit(params, controller, rho0, v0, keys, nominal, n_steps: int, record_every: int,
                        axes: tuple, chunk_size: int = 0) -> SimResult:
    def one(p, c, r, v, k):
        return _simulate(p, c, r, v, k, nominal, n_steps, record_every)

    return chunked_vmap(one, (params, controller, rho0, v0, keys), axes, chunk_size)


def chunked_vmap(fn, args: tuple, axes: tuple, chunk_size: int) -> Any:
    """``jax.vmap(fn, in_axes=axes)(*args)`` computed as a sequential ``lax.map`` over chunks of
    ``chunk_size`` batch entries (``axes`` entries are 0 or None; outputs get a leading batch axis).

    Chunk j holds the entries j, j + n_chunks, j + 2 n_chunks, ... (a strided split), so that a
    batch sharded in contiguous blocks over several devices gives every device its share of
    every chunk. A batch that is not a multiple of ``chunk_size`` is padded with copies of its
    last entry, whose results are dropped. ``chunk_size`` <= 0 or >= the batch: a plain vmap.
    """
    idx = [i for i, ax in enumerate(axes) if ax is not None]
    batched = [args[i] for i in idx]
    size = jax.tree_util.tree_leaves(batched)[0].shape[0]
    if chunk_size <= 0 or size <= chunk_size:
        return jax.vmap(fn, in_axes=axes)(*args)
    n_chunks = -(-size // chunk_size)
    pad = n_chunks * chunk_size - size

    def split(x):
        if pad:
            x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
        return jnp.swapaxes(x.reshape((chunk_size, n_chunks) + x.shape[1:]), 0, 1)

    def run_chunk(chunk):
        full = list(args)
        for i, a in zip(idx, chunk, strict=True):
            full[i] = a
        return jax.vmap(fn, in_axes=axes)(*full)

    out = jax.lax.map(run_chunk, jax.tree.map(split, batched))

    def merge(y):
        return jnp.swapaxes(y, 0, 1).reshape((n_chunks * chunk_size,) + y.shape[2:])[:size]

    return jax.tree.map(merge, out)


def stack_params(**fields: Any) -> TrafficParams:
    """A batched ``TrafficParams``: each keyword is a sequence of per-environment values (or a
    scalar, shared by every environment); the others keep their defaults (broadcast). Static
    fields are passed as scalars. At least one field must be a sequence."""
    static = {k: fields.pop(k) for k in ("n_points", "max_delay_steps", "scheme", "model") if k in fields}
    arrays = {k: np.asarray(v, np.float64) for k, v in fields.items()}
    sizes = {a.shape[0] for a in arrays.values() if a.ndim == 1}
    if any(a.ndim > 1 for a in arrays.values()):
        raise ValueError("stack_params: each field must be a scalar or a 1-d sequence")
    if len(sizes) != 1:
        raise ValueError(f"all batched fields need the same length (and at least one is needed), got {sizes}")
    (b,) = sizes
    arrays = {k: np.broadcast_to(a, (b,)) for k, a in arrays.items()}
    base = TrafficParams(**static)
    # validate every concrete environment before building the traced batch
    for i in range(b):
        base.replace(**{k: np.asarray(a[i]).item() for k, a in arrays.items()})
    full = {f: jnp.broadcast_to(jnp.asarray(getattr(base, f), float), (b,))
            for f in base.__dataclass_fields__ if f not in ("n_points", "max_delay_steps", "scheme", "model")}
    full.update({k: jnp.asarray(a, float) for k, a in arrays.items()})
    return base.replace(**full)
