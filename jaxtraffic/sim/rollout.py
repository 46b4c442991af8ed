"""Batched closed-loop rollouts in ``lax.scan`` (docs/model.md sections 4, 5, 10).

``simulate`` runs one environment; ``simulate_batch`` vmaps it over a batch of parameters,
initial states, keys and (optionally) controller settings. Both are jit-compiled; the number of
steps and the recording stride are static, every physical constant, delay and gain is traced.
Each step is ``sim.plant.closed_loop_step`` (the order of a step is described there); the plant
alphas of all steps are drawn at once, before the loop, from the plant's key, and the metrics
(``sim.metrics``) accumulate while the rollout streams.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh

from jaxtraffic.control.base import Controller
from jaxtraffic.control.baselines import check_assumed_delay, open_loop
from jaxtraffic.model.fundamental import in_physical_region
from jaxtraffic.model.params import TrafficParams, check_nominal, check_steps, equilibrium
from jaxtraffic.platform.tracing import is_traced
from jaxtraffic.sim import metrics
from jaxtraffic.sim.batching import chunked_vmap, stack_params
from jaxtraffic.sim.initial import equilibrium_state, paper_initial_condition
from jaxtraffic.sim.metrics import select_metrics
from jaxtraffic.sim.options import AlphaInput, Memory, Record
from jaxtraffic.sim.outcome import DivergedError, Divergence, check_outcome
from jaxtraffic.sim.plant import (
    NoiseReading,
    PlantState,
    closed_loop_step,
    initial_state,
    noise_alpha_sequence,
    plant_step,
)
from jaxtraffic.sim.sharding import (
    batch_mesh,
    gathered,
    host_mesh,
    local_copy,
    replicate,
    sharded_batch,
    spans_processes,
)

Array = jax.Array

__all__ = ["AlphaInput", "DivergedError", "Divergence", "Memory", "NoiseReading", "PlantState", "Record", "SimResult",
           "Trajectory", "check_outcome", "chunked_vmap", "equilibrium_state", "finalize_metrics", "initial_state",
           "paper_initial_condition", "plant_alphas", "plant_step", "simulate", "simulate_batch", "stack_params"]


@struct.dataclass
class Trajectory:
    """Every ``Record.every``-th step from t = 0: t (s), rho (veh/m), v (m/s), h (sent, s),
    reward, rho_L2 (veh/km, like every density metric) and v_L2 (m/s)."""

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
    the final controller state and the trajectory (None unless ``record=Record(every > 0)``)."""

    metrics: dict
    final: PlantState
    controller_state: Any
    trajectory: Trajectory | None


def finalize_metrics(acc: metrics.MetricsAccumulator, final: PlantState, target: TrafficParams,
                     n_steps: int, dx: Array | float | None = None, names: tuple[str, ...] | None = None) -> dict:
    """Scalar results of a rollout (``dx``: the plant's grid spacing, default ``target.dx``): those of
    ``names`` (default: all, ``metrics.METRIC_NAMES``) whose running sums ``acc`` keeps, in that order.

    J_TTT, J_fuel, J_comfort (rho in veh/km; see ``metrics``), final_rho_L2 (veh/km),
    final_v_L2 (m/s), final_reward, time_to_reward_target_s (time after which the reward stays
    >= -0.1; inf if it never does), diverged, diverged_at_s (inf if never), diverged_reason
    (int32 code of ``sim.outcome.Divergence``: 0 healthy, 1 state left the physical region, 2 controller
    output not finite, 3 initial state not finite/physical, 4 parameters invalid), control_effort
    (RMS over space and time of h_sent - h_bar, s), max_cfl (largest CFL number of the steps
    taken, with the applied input and the plant's alpha); then ``metrics.EXTRA_INDICES`` (the
    comfort parts, the switch-on step and the paper's km/h reading); only when asked for (``names``):
    late_max_rho_std (veh/km, ``metrics.late_max``: max of std_x(rho) over the last ``metrics.LATE_WINDOW_S``).
    """
    dx = target.dx if dx is None else dx
    rho_bar, v_bar = equilibrium(target)
    dt = target.dt

    def r_final():
        return metrics.reward(final.rho, final.v, rho_bar, v_bar, dx)

    def time_to_target():
        reached = ~final.diverged & (acc.last_bad_step < n_steps - 1) & (r_final() >= metrics.REWARD_TARGET)
        return jnp.where(reached, (acc.last_bad_step + 1) * dt, jnp.inf)

    tot = metrics.totals(acc, dx)
    table = {
        "final_rho_L2": lambda: metrics.density_l2(final.rho, rho_bar),
        "final_v_L2": lambda: metrics.l2_deviation(final.v, v_bar),
        "final_reward": r_final,
        "time_to_reward_target_s": time_to_target,
        "diverged": lambda: final.diverged,
        "diverged_at_s": lambda: jnp.where(final.diverged, final.diverged_step * dt, jnp.inf),
        "diverged_reason": lambda: final.diverged_reason,
        "late_max_rho_std": lambda: metrics.late_max(acc, final.rho, final.diverged),
    }
    names = metrics.METRIC_NAMES if names is None else names
    return {k: tot[k] if k in tot else table[k]() for k in names if k in tot or k in table and metrics.kept(acc, k)}


def plant_alphas(params: TrafficParams, key: Array | None, n_steps: int, noise: NoiseReading | None = None,
                 dtype: Any = jnp.float32) -> Array:
    """The plant alphas a rollout with this ``key`` (default PRNGKey(0)) and ``noise`` reading draws:
    shape (n_steps,), or (n_steps, n) per node (``sim.plant.noise_alpha_sequence`` on the plant half
    of the key; the other half goes to the controller). Giving them back as ``alphas=`` reproduces
    that rollout, so rollouts of different (road-wide) readings can share one compiled program."""
    key = jax.random.PRNGKey(0) if key is None else key
    return noise_alpha_sequence(params, jax.random.split(key)[0], n_steps, noise, dtype)


def _simulate(params: TrafficParams, controller: Controller | None, rho0: Array | None,
              v0: Array | None, key: Array | None, nominal: TrafficParams | None,
              n_steps: int, record_every: int, remat: bool = False,
              noise: NoiseReading | None = None, alphas: Array | None = None,
              names: tuple[str, ...] = metrics.METRIC_NAMES) -> SimResult:
    p = params
    nominal = p if nominal is None else nominal
    controller = open_loop() if controller is None else controller
    if rho0 is None:
        rho0, v0 = paper_initial_condition(p)
    assert v0 is not None  # both or neither (_check_rollout_args)
    key = jax.random.PRNGKey(0) if key is None else key
    k_ctrl = jax.random.split(key)[1]
    rho_bar, v_bar = equilibrium(nominal)
    state = initial_state(p, rho0, v0)
    cstate = controller.init(state.observation(p), nominal)
    acc = metrics.init_metrics(p.n_points, rho0.dtype, metrics.accumulators(names))  # only the sums `names` read
    if acc.last_bad_step is not None:
        # rewards are tracked for the state after each step (sharing the physicality reduction);
        # the initial state's is counted here
        r0 = metrics.reward(rho0, v0, rho_bar, v_bar, p.dx)
        acc = acc.replace(last_bad_step=jnp.where(r0 < metrics.REWARD_TARGET, 0, -1).astype(jnp.int32))
    # the plant's alpha of every step, drawn at once (cheaper than a draw inside the loop), unless given
    alphas = plant_alphas(p, key, n_steps, noise, rho0.dtype) if alphas is None else alphas.astype(rho0.dtype)
    sees = noise is not None and noise.model_sees
    target = metrics.MetricsTarget(rho_bar=rho_bar, v_bar=v_bar, h_bar=nominal.h_bar, dx=p.dx, dt=p.dt,
                                   switch_step=p.delay_steps, late_step=n_steps - metrics.late_steps(p.dt))

    def one_step(carry, alpha_n):
        state, cstate, acc = carry
        n = state.step
        new, cstate, h, info = closed_loop_step(state, cstate, controller, p, nominal, alpha_n,
                                                jax.random.fold_in(k_ctrl, n), (rho_bar, v_bar), sees)
        active = ~new.diverged
        record = metrics.StepRecord(step=n, rho=state.rho, v=state.v, v_next=new.v, h_sent=h, cfl=info.cfl,
                                    active=active, reward_next=info.reward)
        acc = metrics.update_metrics(acc, record, target)
        return (new, cstate, acc), h

    carry = (state, cstate, acc)
    traj = None
    if record_every:
        if n_steps % record_every:
            raise ValueError(f"n_steps={n_steps} is not a multiple of record_every={record_every}")

        def chunk(carry, alpha_chunk):
            s = carry[0]
            carry, hs = jax.lax.scan(one_step, carry, alpha_chunk)
            rec = (s.step * p.dt, s.rho, s.v, hs[0], metrics.reward(s.rho, s.v, rho_bar, v_bar, p.dx),
                   metrics.density_l2(s.rho, rho_bar), metrics.l2_deviation(s.v, v_bar))
            return carry, rec

        # remat: reverse-mode differentiation keeps only the carry at chunk boundaries and recomputes
        # the steps of one chunk at a time (memory O(n_steps / record_every + record_every))
        chunk_fn = jax.checkpoint(chunk) if remat else chunk
        chunks = alphas.reshape((n_steps // record_every, record_every) + alphas.shape[1:])
        carry, rec = jax.lax.scan(chunk_fn, carry, chunks)
        traj = Trajectory(*rec)
    else:
        carry, _ = jax.lax.scan(lambda c, x: (one_step(c, x)[0], None), carry, alphas)
    state, cstate, acc = carry
    return SimResult(metrics=finalize_metrics(acc, state, nominal, n_steps, p.dx, names), final=state,
                     controller_state=cstate, trajectory=traj)


_simulate_jit = jax.jit(_simulate, static_argnames=("n_steps", "record_every", "remat", "noise", "names"))


def _check_alphas(params: TrafficParams, alphas: Array | None, n_steps: int, noise: NoiseReading | None,
                  batched: bool) -> None:
    """ValueError unless ``alphas`` is None or of shape ([B,] n_steps[, n_points]) (B when ``batched``),
    and ``noise`` does not also ask for a draw of its own (held or per node)."""
    if alphas is None:
        return
    if noise is not None and (noise.hold_steps != 1 or noise.per_node):
        raise ValueError("alphas replaces the drawn alpha noise: give it the reading's sequence "
                         "(plant_alphas(..., noise=reading)) and leave noise to model_sees")
    shape = tuple(jnp.shape(alphas))
    ok = ((n_steps,), (n_steps, params.n_points))
    if (shape[1:] if batched else shape) not in ok:
        lead = "(B, ...) with " if batched else ""
        raise ValueError(f"alphas needs shape {lead}{ok[0]} or {ok[1]}, got {shape}")
    if not is_traced(alphas):  # (traced sequences are not checked)
        a = np.asarray(alphas, np.float64)
        if not np.all((a >= 0) & (a <= 1)):
            raise ValueError(f"alphas must lie in [0, 1] (ACC shares), got values in [{np.nanmin(a):g}, "
                             f"{np.nanmax(a):g}]" + (" and NaN" if np.isnan(a).any() else ""))


def _check_initial_condition(params: TrafficParams, rho0: Array | None, v0: Array | None) -> None:
    """Raise ``ValueError`` if a concrete initial state (single, or batched (B, n)) is not finite
    or outside 0 < rho < 1/l, v >= 0. Traced inputs are not checked (the rollout then flags
    such an environment as diverged at step 0)."""
    if rho0 is None or is_traced(rho0, v0, params.l):
        return
    r, v = np.asarray(rho0, np.float64), np.asarray(v0, np.float64)
    if r.shape[-1] != params.n_points or v.shape[-1] != params.n_points:
        raise ValueError(f"rho0 and v0 need {params.n_points} points, got shapes {r.shape}, {v.shape}")
    l = np.asarray(params.l, np.float64)
    if l.ndim == 1:  # batched parameters
        l = l[:, None]
    ok = np.all(in_physical_region(r, v, l), axis=-1)
    if not np.all(ok):
        which = "" if np.ndim(ok) == 0 else f" in environment(s) {np.flatnonzero(~ok).tolist()}"
        raise ValueError("initial state outside the physical region (finite, 0 < rho < 1/l, v >= 0)" + which)


def simulate(
    params: TrafficParams, controller: Controller | None = None, *, n_steps: int,
    rho0: Array | None = None, v0: Array | None = None, key: Array | None = None,
    nominal: TrafficParams | None = None, record: Record | None = None, memory: Memory | None = None,
    alpha_input: AlphaInput | None = None, metrics: Iterable[str] | str | None = None,
) -> SimResult:
    """Closed-loop rollout of one freeway for ``n_steps`` steps of ``params.dt``.

    Args:
        params: the plant (its alpha, alpha_noise and delay are the true ones).
        controller: a ``Controller`` (default: open loop).
        n_steps: number of steps (static).
        rho0: initial density (veh/m), shape (n_points,) (default: the paper's initial condition).
        v0: initial speed (m/s), shape (n_points,) (default: the paper's initial condition).
        key: PRNG key for alpha noise and stochastic controllers (default PRNGKey(0)).
        nominal: the parameters the controller and the metrics use as model and target
            (default: ``params``). docs/model.md section 12: keep the nominal target when the
            plant's alpha differs. It must be on the plant's grid (same n_points, dt, L).
        record: ``Record(every=k)``: record the fields every k-th step into ``trajectory``
            (default: none, metrics only).
        memory: ``Memory(remat=True)`` checkpoints every recording chunk for reverse-mode
            differentiation (its ``chunk_size`` only matters to ``simulate_batch``).
        alpha_input: ``AlphaInput(alphas=..., noise=...)``: the plant's alpha of every step, shape
            (n_steps,) or (n_steps, n_points), instead of a draw, and/or the ``NoiseReading`` of the draw
            (default: one road-wide draw per step, plant only).
        metrics: the names of the metrics to compute (static; ``sim.metrics.METRIC_NAMES``; default all of
            them): only the running sums they read are carried through the loop, and each one kept has the
            value it has in the default call. ``()``: none (the bare closed loop).
    Returns:
        A ``SimResult``: scalar metrics (``finalize_metrics``), final plant and controller states, and
        the trajectory (None without ``record``). A diverged rollout is flagged, not raised
        (``metrics["diverged_reason"]``; ``sim.outcome.check_outcome`` raises on it).
    Raises:
        ValueError: for invalid arguments (steps, nominal grid, initial state, alphas, remat without record,
            an unknown metric name).
    """
    names = select_metrics(metrics)
    record, memory, alpha_input = _options(record, memory, alpha_input)
    _check_rollout_args(params, n_steps, rho0, v0, nominal, record, memory)
    _check_controller(controller, batched=False)
    check_assumed_delay(controller, params)
    _check_alphas(params, alpha_input.alphas, int(n_steps), alpha_input.noise, batched=False)
    return _simulate_jit(params, controller, rho0, v0, key, nominal, int(n_steps), record.every, memory.remat,
                         alpha_input.noise, alpha_input.alphas, names)


_Option = TypeVar("_Option", Record, Memory, AlphaInput)


def _options(record: Record | None, memory: Memory | None, alpha_input: AlphaInput | None
             ) -> tuple[Record, Memory, AlphaInput]:
    """The option objects with their defaults filled in; TypeError for another type (e.g. a bare int)."""
    return (_option("record", record, Record), _option("memory", memory, Memory),
            _option("alpha_input", alpha_input, AlphaInput))


def _option(name: str, value: object, cls: type[_Option]) -> _Option:
    value = cls() if value is None else value
    if not isinstance(value, cls):
        raise TypeError(f"{name} must be a {cls.__name__} (sim.options), got {type(value).__name__}")
    return value


def _check_rollout_args(params, n_steps, rho0, v0, nominal, record: Record, memory: Memory) -> None:
    """The argument checks ``simulate`` and ``simulate_batch`` share (ValueError with the reason)."""
    if memory.remat and not record.every:
        raise ValueError("remat needs record_every > 0 (the checkpointed chunk length): pass record=Record(every=k)")
    if (rho0 is None) != (v0 is None):
        raise ValueError("give both rho0 and v0, or neither")
    check_steps(n_steps, record.every)
    check_nominal(params, nominal)
    _check_initial_condition(params, rho0, v0)


def _check_controller(controller: object, batched: bool) -> None:
    """``TypeError`` unless ``controller`` is a ``Controller`` (or None: the open loop); with ``batched``
    (``batch_controller=True``) ``ValueError`` unless every leaf of its settings has a leading batch axis."""
    if controller is not None and not isinstance(controller, Controller):
        raise TypeError(f"controller must be a jaxtraffic Controller (jt.backstepping(4.0), jt.lyapunov(1.0), "
                        f"control.base.Controller(...)) or None for the open loop, got {type(controller).__name__}")
    if not batched:
        return
    leaves = jax.tree_util.tree_leaves(controller.settings) if isinstance(controller, Controller) else []
    # (a controller without settings, the open loop's, has nothing to batch: accepted)
    if controller is None or any(jnp.ndim(x) == 0 for x in leaves):
        raise ValueError("batch_controller=True needs a controller whose settings carry a leading batch axis "
                         "(e.g. jax.vmap(jt.backstepping)(delays)); this one's are unbatched (a scalar setting, or "
                         "no controller): give batch_controller=False to share it")


def simulate_batch(
    params: TrafficParams, controller: Controller | None = None, *, n_steps: int,
    rho0: Array | None = None, v0: Array | None = None, keys: Array | None = None,
    nominal: TrafficParams | None = None, batch_controller: bool = False, record: Record | None = None,
    memory: Memory | None = None, alpha_input: AlphaInput | None = None, metrics: Iterable[str] | str | None = None,
) -> SimResult:
    """``simulate`` vmapped over a batch; every returned leaf gets a leading batch axis.

    Batched inputs are recognised by shape: ``params`` whose float leaves have one axis (build
    them with ``stack_params``), ``rho0``/``v0`` of shape (B, n_points), ``keys`` of shape (B, 2).
    The controller is batched only when ``batch_controller`` is set (its settings then carry
    a leading batch axis). ``nominal`` is shared (not batched). At least one input must be batched.
    The arguments not below are ``simulate``'s (``keys`` instead of ``key``).

    Args:
        record: as ``simulate`` (shared by every environment).
        memory: ``Memory(remat, chunk_size)``. ``chunk_size`` (static; default "auto": 64 on a CPU, none on
            an accelerator, ``Memory.chunk_for``): a batch larger than this runs as a sequential loop over
            chunks of ``chunk_size`` environments, each chunk vmapped over the whole rollout, so that the
            working set of a chunk stays in cache (on a CPU this is 1.5-3x faster for large batches than one
            vmap over everything; a GPU wants the whole batch at once). ``None`` or 0: a single vmap.
            Results do not depend on it beyond rounding, and every environment stays independent of the
            others. ``remat`` (static, needs ``record``): checkpoint each recording chunk for reverse-mode
            differentiation (``jax.checkpoint``), so that the memory of a gradient grows with
            n_steps / every + every steps instead of n_steps. Values are unchanged.
        alpha_input: its ``noise`` reading is shared by every environment; its ``alphas``, if given, are
            every environment's plant alphas, shape (B, n_steps) or (B, n_steps, n_points) (environments
            whose alpha sequences come from different road-wide readings can so share one program).
    Returns:
        A ``SimResult`` whose every leaf has a leading batch axis B.
    Raises:
        ValueError: if nothing is batched, or for the invalid arguments ``simulate`` rejects.

    Devices (``sim.sharding``): the batch is split over this process's devices; called with
    concrete inputs in a multi-process run, over every device of every process, each process
    getting the whole result as local arrays (every process must make the same call).
    """
    names = select_metrics(metrics)
    record, memory, alpha_input = _options(record, memory, alpha_input)
    alphas, noise = alpha_input.alphas, alpha_input.noise
    p_axis = 0 if jnp.ndim(jax.tree_util.tree_leaves(params)[0]) == 1 else None
    r_axis = 0 if rho0 is not None and jnp.ndim(rho0) == 2 else None
    k_axis = 0 if keys is not None and jnp.ndim(keys) == 2 else None
    c_axis = 0 if batch_controller else None
    a_axis = None if alphas is None else 0
    if (p_axis, r_axis, k_axis, c_axis, a_axis) == (None,) * 5:
        raise ValueError("simulate_batch: nothing is batched; use simulate")
    _check_rollout_args(params, n_steps, rho0, v0, nominal, record, memory)
    _check_controller(controller, batched=batch_controller)
    check_assumed_delay(controller, params)
    _check_alphas(params, alphas, int(n_steps), noise, batched=True)
    inputs = (params, controller, rho0, v0, keys, nominal, alphas)
    mesh = host_mesh(inputs)  # every process's devices in a multi-process run (sim.sharding)
    across = spans_processes(mesh)
    res = _simulate_batch_jit(*(replicate(inputs, mesh) if across else inputs), int(n_steps), record.every,
                              (p_axis, c_axis, r_axis, r_axis, k_axis, a_axis),
                              memory.chunk_for(mesh.devices.flat[0].platform), memory.remat, noise, mesh, names)
    return local_copy(res) if across else res


@functools.partial(jax.jit, static_argnames=("n_steps", "record_every", "axes", "chunk_size", "remat", "noise",
                                             "mesh", "names"))
def _simulate_batch_jit(params, controller, rho0, v0, keys, nominal, alphas, n_steps: int, record_every: int,
                        axes: tuple, chunk_size: int = 0, remat: bool = False, noise: NoiseReading | None = None,
                        mesh: Mesh | None = None, names: tuple[str, ...] = metrics.METRIC_NAMES) -> SimResult:
    def one(p, c, r, v, k, a):
        return _simulate(p, c, r, v, k, nominal, n_steps, record_every, remat, noise, a, names)

    def local(*args):  # this device's block of the batch
        return chunked_vmap(one, args, axes, chunk_size)

    mesh = batch_mesh() if mesh is None else mesh
    return gathered(sharded_batch(local, (params, controller, rho0, v0, keys, alphas), axes, mesh), mesh)
