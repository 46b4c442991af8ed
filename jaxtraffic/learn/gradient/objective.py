"""Gradient-based training through the differentiable simulator (analytic policy gradients).

The plant (ARZ solver, delay buffer, gain law, metrics) is pure JAX, so ``jax.grad`` of a rollout
objective with respect to the controller's parameters is exact (to rounding) and cheap: one
forward and one backward pass of a batched ``simulate_batch`` over a grid of training scenarios.
Two policies are trained this way:

* ``"gains"``: the paper's three-gain law with three constant gains (eta1, eta2, eta3);
* ``"network"``: the same actor network PPO trains (``control.networks.ActorCritic``; its critic is not
  used), whose deterministic gains grad_gain_max * tanh(mean) pass through the same first-order gain
  filter as PPO's and act through the same three-gain law (``control.gain_policy.policy_controller``);
* ``"schedule"``: a family of gain triples scheduled in the input delay (``control.gain_law.scheduled_gains``:
  a (K, 3) table at the ``schedule_knots``, interpolated at the delay the controller is told). In training every
  scenario's controller is told its plant's delay; it is not told the plant's alpha. Its defaults train it
  over the robustness map's ranges of delay and alpha on scenarios offset from both maps' cells.

Objective (minimised, dimensionless), averaged over the training scenarios s:

    J = mean_s [ -w_r mean_k r_s(t_k)  +  w_w mean_k log(1 + var_x rho_s(t_k) / 100 + var_x v_s(t_k))
                 +  w_c J_comfort_s ]

with r the paper's reward (dimensionless) sampled every ``record_every`` steps t_k, var_x the
spatial variance of density (veh/km)^2 and speed (m/s)^2 (the "waves" term: zero for any uniform
state, so it does not penalise the steady offset a plant with another alpha settles to; its mean over k
is weighted by t_k / T, so that late waves, which the robustness map judges, count most),
J_comfort in the units of ``metrics`` (rho in veh/km, a in m/s^2), sampled every ``record_every`` steps.
The weights w_r, w_w, w_c are ``reward_weight``, ``waves_weight``, ``comfort_weight`` (``Weights``; defaults
1, 0, 1e-5).

Memory: the rollout checkpoints every recording chunk (``simulate(memory=Memory(remat=True))``), so the
backward pass stores the carry once per chunk and recomputes one chunk at a time.
Divergence containment (``sim.plant``) freezes an environment at its last physical state; the
frozen branch and the unphysical branch are both finite, so the gradient stays finite when a
scenario diverges (tested). Adam with global-norm gradient clipping.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh

from jaxtraffic.compare.scenarios import EpisodePool
from jaxtraffic.control.adapter import ControllerGrid, on_grid
from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_policy import equilibrium_gains
from jaxtraffic.control.noise import sensor_noise
from jaxtraffic.control.stability import GROWTH_TOL, model_growth_rates, wavenumbers
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.learn.gradient.policies import OBS_SCALE, POLICIES, obs_statistics  # noqa: F401 (re-exported)
from jaxtraffic.model.linear import linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.model.solver import is_physical
from jaxtraffic.platform.tracing import is_traced
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM
from jaxtraffic.sim.options import Memory, Record
from jaxtraffic.sim.rollout import simulate
from jaxtraffic.sim.sharding import batch_mesh, gathered, local_copy, replicate, sharded_batch, spans_processes

Array = jax.Array
# the rollout metrics the objective computes: J_comfort (its comfort term) and final-state ones, which cost no
# running sum in the loop (reported per scenario in the training chunk's metrics)
OBJECTIVE_METRICS = ("J_comfort", "final_rho_L2", "final_reward", "diverged")
# m: the road of every training config (runs.config has no road-length field); the filter's width in nodes
# is static, so it is computed from this rather than from the traced base.L
ROAD_LENGTH = float(TrafficParams().L)


@struct.dataclass
class Weights:
    """Traced objective weights (see the module docstring)."""

    reward_weight: Array
    waves_weight: Array
    comfort_weight: Array


@struct.dataclass
class Scenarios:
    """A batch of training plants: batched ``TrafficParams``, initial fields (B, n), and the sensor noise each
    scenario's law sees (``noise``: relative levels (B,), ``keys``: PRNG keys (B, 2); ``noisy``)."""

    params: TrafficParams
    rho0: Array
    v0: Array
    noise: Array
    keys: Array


def noisy(grad_config: GradientConfig) -> bool:
    """Whether the training scenarios are seen with sensor noise (static: the controller is wrapped only then)."""
    return grad_config.train_sensor_noise[1] > 0


@struct.dataclass
class GradState:
    """Trainable parameters (``theta``: gains (3,) or flax params), Adam state, update count."""

    theta: Any
    opt_state: Any
    update: Array


def training_scenarios(grad_config: GradientConfig, base: TrafficParams, pool: EpisodePool | None = None
                       ) -> Scenarios:
    """The scenario grid of ``grad_config`` on the grid of ``base`` (alpha noise off), or its ``train_split``
    scenarios of the train split: ``pool`` (``train_pool``), drawn here when None (``base`` concrete). Sensor
    noise (``train_sensor_noise``) needs the split: ``ValueError`` on the grid."""
    if grad_config.train_split:
        pool = train_pool(grad_config, base) if pool is None else pool
        assert pool is not None
        batched = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, pool.rho0.dtype), pool.delay.shape),
                               base.replace(alpha_noise=0.0))
        return Scenarios(params=batched.replace(delay=pool.delay, alpha=pool.alpha), rho0=pool.rho0, v0=pool.v0,
                         noise=pool.noise, keys=pool.keys)
    if noisy(grad_config):
        raise ValueError(f"train_sensor_noise = {grad_config.train_sensor_noise}: needs train_split > 0 (the grid of "
                         "scenarios has no noise draws)")
    amps_m = tuple(a / VEH_PER_KM for a in grad_config.train_amplitudes)  # veh/km -> veh/m, the simulator's unit
    grid = list(itertools.product(grad_config.train_delays, grad_config.train_alphas, amps_m,
                                  grad_config.train_wavenumbers, grad_config.train_phases))
    dtype = jnp.result_type(float)  # float32, or float64 under jax.enable_x64
    delays, alphas, amps, wns, phases = (jnp.asarray(c, dtype) for c in zip(*grid, strict=True))
    b = len(grid)
    batched = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, dtype), (b,)), base.replace(alpha_noise=0.0))
    params = batched.replace(delay=jnp.round(delays / base.dt) * base.dt, alpha=alphas)
    rho0, v0 = jax.vmap(lambda a, k, ph: paper_initial_condition(base, a, k, ph, dtype))(amps, wns, phases)
    return Scenarios(params=params, rho0=rho0, v0=v0, noise=jnp.zeros((b,), jnp.float32),
                     keys=jax.random.split(jax.random.PRNGKey(0), b))


def train_pool(grad_config: GradientConfig, base: TrafficParams) -> EpisodePool | None:
    """The train-split scenarios of ``grad_config`` on ``base``'s grid (``base`` concrete: drawn on the host, then
    passed traced to the compiled training), or None for the scenario grid (built inside the compiled program)."""
    return EpisodePool.train_split(grad_config.train_split, base, grad_config.train_sensor_noise) \
        if grad_config.train_split else None


def init_theta(grad_config: GradientConfig, base: TrafficParams, key: Array) -> Any:
    """Initial parameters of the policy (``policies.POLICIES``): the gains ``init_gains``, a schedule or residual
    table of them, or a network whose output is (nearly) those gains everywhere."""
    g0 = jnp.asarray(grad_config.init_gains, jnp.result_type(float))
    return POLICIES[grad_config.policy].init(grad_config, grad_config.controller_points or base.n_points, g0, key)


def trainable(grad_config: GradientConfig, theta: Array) -> Array | float:
    """1 where a parameter is trained, 0 where it is held at zero (a residual's rows below
    ``residual_alpha_floor``: the adaptive law there; broadcasts against its table)."""
    return POLICIES[grad_config.policy].mask(grad_config, theta)


def own_controller(theta: Any, grad_config: GradientConfig, n_points: int, dx: float, delay: float | Array = 4.0
                   ) -> Controller:
    """The controller of parameters ``theta`` (deterministic) on its own grid of ``n_points`` nodes, spacing
    ``dx`` (m, for the filter width in nodes); ``delay`` (s): the delay a schedule is told."""
    return POLICIES[grad_config.policy].controller(theta, grad_config, n_points, dx, delay)


def fixed_gains(theta: Any, grad_config: GradientConfig, delay: float | Array) -> Array | None:
    """The gains (3,) the policy applies when told ``delay`` (s); None for a network (its gains depend on the
    state); for a residual, its correction's [0, eta2, eta3] at the initial estimate."""
    return POLICIES[grad_config.policy].gains(theta, grad_config, delay)


def make_controller(theta: Any, grad_config: GradientConfig, base: TrafficParams, delay: float | Array | None = None,
                    noise: float | Array | None = None) -> Controller:
    """The controller of parameters ``theta`` on its own grid, acting on the plant grid of ``base``
    (``control.adapter.on_grid``: restricted observation, interpolated time gap; the period is dt);
    ``delay`` (s): the delay a schedule is told (default ``base.delay``); ``noise``: the relative sensor error it
    sees on its own grid (``control.noise.sensor_noise``; None: none)."""
    check_road(base)
    n = grad_config.controller_points or base.n_points
    r = (base.n_points - 1) // (n - 1)
    ctrl = own_controller(theta, grad_config, n, ROAD_LENGTH / (n - 1), base.delay if delay is None else delay)
    ctrl = ctrl if noise is None else sensor_noise(ctrl, noise)
    return ctrl if r == 1 else on_grid(ctrl, ControllerGrid(n, 0.0, base.max_delay_steps), r, 1)


def weights_of(grad_config: GradientConfig) -> Weights:
    return Weights(**{f.name: jnp.asarray(getattr(grad_config, f.name),
                                          jnp.float32) for f in dataclasses.fields(Weights)})


def check_road(base: TrafficParams) -> None:
    """``ValueError`` unless ``base`` is on the road the gradient-trained controllers are built for (``L`` =
    ``ROAD_LENGTH`` m: their filter and certificate use it); a traced ``L`` is not checked."""
    length = None if is_traced(base.L) else np.asarray(base.L, np.float64)
    if length is not None and not np.allclose(length, ROAD_LENGTH, rtol=1e-9):
        raise ValueError(f"L = {length.tolist()} m: the gradient-trained controllers are built for the paper's road, "
                         f"L = {ROAD_LENGTH:g} m (objective.ROAD_LENGTH); another road length is not supported")


def check_scenarios(grad_config: GradientConfig, base: TrafficParams) -> None:
    """``ValueError`` naming the field if a training scenario is one the plant cannot represent: sensor noise
    without the train split, a delay beyond the buffer, an initial state outside the physical region, a sampling
    interval longer than the horizon, a road of another length (``check_road``)."""
    check_road(base)
    cap = base.max_delay_steps
    beyond = [d for d in grad_config.train_delays if round(d / float(base.dt)) > cap]
    if beyond:
        raise ValueError(f"train_delays = {beyond}: beyond the delay buffer's "
                         f"{cap * float(base.dt):g} s (max_delay_steps {cap} x dt {float(base.dt):g} s); raise "
                         "max_delay_steps")
    if grad_config.record_every * float(base.dt) > grad_config.train_horizon_s:
        raise ValueError(f"record_every = {grad_config.record_every}: must be <= the training horizon "
                         f"(train_horizon_s {grad_config.train_horizon_s:g} s = "
                         f"{round(grad_config.train_horizon_s / float(base.dt))} steps)")
    sc = training_scenarios(grad_config, base)
    if not bool(jnp.all(jax.vmap(is_physical)(sc.rho0, sc.v0, sc.params))):
        raise ValueError(f"train_amplitudes = {list(grad_config.train_amplitudes)} (veh/km): "
                         "an initial state leaves the physical region (0 < rho < 1/l, v >= 0); use smaller amplitudes")


def horizon_steps(grad_config: GradientConfig, dt: float) -> int:
    """Rollout length of the objective: ``train_horizon_s`` / dt rounded to a multiple of ``record_every``."""
    return max(grad_config.record_every,
               round(grad_config.train_horizon_s / float(dt) / grad_config.record_every) * grad_config.record_every)


def scenario_objective(theta: Any, params: TrafficParams, rho0: Array, v0: Array, noise: Array, key: Array,
                       w: Weights, grad_config: GradientConfig, base: TrafficParams, n_steps: int, remat: bool = True
                       ) -> tuple[Array, dict]:
    """(J_s, metrics) of one scenario (plant ``params``, initial fields (n,), the sensor noise ``noise`` and its
    ``key``, read when ``noisy``); see the module docstring."""
    seen = noisy(grad_config)
    res = simulate(params, make_controller(theta, grad_config, base, params.delay, noise if seen else None),
                   n_steps=n_steps, rho0=rho0, v0=v0, key=key if seen else None, nominal=base,
                   record=Record(every=grad_config.record_every), memory=Memory(remat=remat), metrics=OBJECTIVE_METRICS)
    tr, m = res.trajectory, res.metrics
    assert tr is not None  # recorded: record_every >= 1
    waves = jnp.log1p(jnp.var(tr.rho * VEH_PER_KM, axis=-1) / 100.0 + jnp.var(tr.v, axis=-1))
    late = jnp.arange(1, waves.shape[0] + 1, dtype=waves.dtype)  # t_k / T up to a factor
    j = (-w.reward_weight * jnp.mean(tr.reward) + w.waves_weight * jnp.sum(late * waves) / jnp.sum(late)
         + w.comfort_weight * m["J_comfort"])
    return j, m


def objective(theta: Any, scen: Scenarios, w: Weights, grad_config: GradientConfig, base: TrafficParams,
              n_steps: int | None = None, remat: bool = True) -> tuple[Array, dict]:
    """(J, per-scenario metrics and ``scenario_objective``) of ``theta``: the mean over the scenarios.
    ``n_steps`` (static; default ``horizon_steps(grad_config, base.dt)``, which needs a concrete dt);
    ``remat``: checkpoint the rollout every ``record_every`` steps (same values and gradients)."""
    n_steps = horizon_steps(grad_config, base.dt) if n_steps is None else n_steps
    per, m = jax.vmap(scenario_objective, (None, 0, 0, 0, 0, 0, None, None, None, None, None))(
        theta, scen.params, scen.rho0, scen.v0, scen.noise, scen.keys, w, grad_config, base, n_steps, remat)
    return jnp.mean(per), {**m, "scenario_objective": per}


def objective_and_grad(theta: Any, scen: Scenarios, w: Weights, grad_config: GradientConfig, base: TrafficParams,
                       n_steps: int, mesh: Mesh | None = None) -> tuple[Array, Any, dict]:
    """(J, dJ/dtheta, metrics): every scenario's value and gradient, the scenarios split over the
    devices of ``mesh`` (``sim.sharding.sharded_batch``; default this process's devices), then the
    mean. With ``grad_config.scenario_clip`` > 0 every scenario's gradient is clipped to that global norm
    before the mean, so that one scenario whose gradient explodes (a closed loop near instability,
    long horizons) cannot dominate the step. Traceable."""
    vg = jax.value_and_grad(scenario_objective, has_aux=True)

    def block(th, p, r, v, e, k):  # one device's scenarios
        return jax.vmap(vg, (None, 0, 0, 0, 0, 0, None, None, None, None))(th, p, r, v, e, k, w, grad_config, base,
                                                                           n_steps)

    (per, m), gs = sharded_batch(block, (theta, scen.params, scen.rho0, scen.v0, scen.noise, scen.keys),
                                 (None, 0, 0, 0, 0, 0), mesh)
    norms = jax.vmap(optax.tree.norm)(gs)
    scale = (jnp.minimum(1.0, grad_config.scenario_clip / jnp.maximum(norms, 1e-30)) if grad_config.scenario_clip > 0
             else jnp.ones_like(norms))
    g = jax.tree.map(lambda x: jnp.mean(x * scale.reshape((-1,) + (1,) * (x.ndim - 1)), axis=0), gs)
    return jnp.mean(per), g, {**m, "scenario_objective": per, "scenario_grad_norm": norms}


def certificate_penalty(theta: Any, grad_config: GradientConfig, base: TrafficParams,
                        periods: tuple[int, ...]) -> Array:
    """max(0, sigma_max - GROWTH_TOL) (1/s): by how much the largest growth rate of the law's certificate
    (``control.stability``, at the gains it settles to at the nominal equilibrium, its filter, every training
    delay of ``periods`` control periods) exceeds the tolerance. Differentiable in ``theta``. Run it on one
    device: XLA's CPU ``eig`` inside a program over several devices waits forever on a collective."""
    n = grad_config.controller_points or base.n_points
    nominal = base.replace(n_points=n, substeps=1)
    gains = fixed_gains(theta, grad_config, base.delay)
    if gains is None:
        gains = equilibrium_gains(own_controller(theta, grad_config, n, ROAD_LENGTH / (n - 1)), nominal)
    lm = linearize(nominal)
    k = jnp.asarray(wavenumbers(ROAD_LENGTH, n=96))

    worst = jnp.max(jnp.stack([jnp.max(model_growth_rates(gains, lm, d, k, grad_config.filter_sigma,
                                                          differentiable=True))
                               for d in periods]))
    return jax.nn.relu(worst - GROWTH_TOL)


penalty_and_grad = jax.jit(jax.value_and_grad(certificate_penalty), static_argnames=("grad_config", "periods"))


def make_optimizer(grad_config: GradientConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(grad_config.max_grad_norm), optax.adam(grad_config.grad_lr))


def _one_step(state: GradState, scen: Scenarios, w: Weights, grad_config: GradientConfig, base: TrafficParams,
              n_steps: int, mesh: Mesh | None) -> tuple[GradState, dict]:
    loss, g, aux = objective_and_grad(state.theta, scen, w, grad_config, base, n_steps, mesh)
    updates, opt_state = make_optimizer(grad_config).update(g, state.opt_state, state.theta)
    new = GradState(theta=optax.apply_updates(state.theta, updates), opt_state=opt_state, update=state.update + 1)
    return new, {"objective": loss, "grad_norm": optax.tree.norm(g), **aux}


@functools.partial(jax.jit, static_argnames=("grad_config", "n_steps", "mesh"))
def _train_chunk(state: GradState, base: TrafficParams, grad_config: GradientConfig, n_steps: int,
                 mesh: Mesh, pool: EpisodePool | None = None) -> tuple[GradState, dict]:
    scen, w = training_scenarios(grad_config, base, pool), weights_of(grad_config)
    out = jax.lax.scan(lambda s, _: _one_step(s, scen, w, grad_config, base, n_steps, mesh), state, None,
                       length=grad_config.steps_per_chunk)
    return gathered(out, mesh)  # the per-scenario metrics whole on every process


@functools.partial(jax.jit, static_argnames=("grad_config",))
def _init(key: Array, base: TrafficParams, grad_config: GradientConfig) -> GradState:
    theta = init_theta(grad_config, base, key)
    return GradState(theta=theta, opt_state=make_optimizer(grad_config).init(theta), update=jnp.zeros((), jnp.int32))


def make_train(grad_config: GradientConfig, base: TrafficParams, devices: list | None = None):
    """``(init, train_chunk)``: ``init(key) -> GradState``; ``train_chunk(state) -> (state,
    metrics)`` runs ``steps_per_chunk`` Adam steps in one jit-compiled ``lax.scan``; metrics are
    per step: objective, gradient norm and the per-scenario metrics of the rollout.

    The scenarios of every step are split over ``devices`` (default: every device of every process,
    ``jax.devices()``; ``sim.sharding``); the state and the metrics are whole on every device, and
    both functions return this process's copy (ordinary local arrays), so the loop around them is
    the same for one process and many (every process calls them in the same order). The
    result depends on the device count only through float rounding.

    ``grad_config`` is static (hashable: a second ``make_train`` with an equal config reuses the compiled
    programs); ``base`` (the nominal plant and grid) is traced.
    """
    n_steps = horizon_steps(grad_config, base.dt)
    mesh = batch_mesh(list(jax.devices()) if devices is None else list(devices))
    across = spans_processes(mesh)
    pool = train_pool(grad_config, base)

    def init(key: Array) -> GradState:
        return _init(key, base, grad_config)

    def train_chunk(state: GradState) -> tuple[GradState, dict]:
        # placed whole on every device, as the chunk returns it: one compiled program for every chunk
        out = _train_chunk(replicate(state, mesh), base, grad_config, n_steps, mesh, pool)
        return local_copy(out) if across else out

    return init, train_chunk
