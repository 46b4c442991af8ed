"""Derivative-free training by the cross-entropy method (CEM) on the robustness map's own criterion.

The map counts a plant as *stabilised* when it did not diverge and its final std_x(rho) is below
``sim.metrics.STABLE_STD`` (0.5 veh/km), and as *diverged* when it left the physical region. Both are counts:
their gradient is zero almost everywhere, and the smooth wave objectives of ``learn.gradient.objective`` trade them
badly (measured, docs/model.md section 17). CEM optimises the counts themselves, on the
training scenarios of a ``GradientConfig`` (plants offset from the map's cells):

    fitness(theta) = #stabilised - DIVERGED_COST #diverged - cem_tie_weight mean_s log(final std_s + 1e-3 veh/km)

(with the default ``cem_tie_weight`` 0.01 the last term only orders laws of equal counts, by how far their waves
decayed; larger, it trades decay against the counts). With ``cem_fitness="mean_l2"`` the fitness is instead the
fair comparison's own measure, the one the tuned baselines minimise (``compare.tuning``): minus the mean over the
scenarios of the time-averaged density L2 over the horizon (veh/km, sampled every ``stats.RECORD_EVERY_S``, capped
at ``stats.L2_CAP``, a diverged scenario counted at the cap; ``stats.capped_mean_l2``). Each generation samples
``cem_population`` parameter sets from a diagonal Gaussian (the current mean is always one of them, so the
mean's own fitness is known), rolls every one out on every scenario (one batched, forward-only
``simulate_batch``), and refits the Gaussian to the best fifth (the elites; a floor
``SIGMA_MIN`` keeps it searching; a residual's rows below ``residual_alpha_floor`` are not sampled: they stay
zero). The policy (``CemState.theta``) is the best parameter set evaluated so far.
Deterministic for a given key. ``make_train`` has the signature of ``objective.make_train``, so the same
host loop (``runs.loop``, through ``runs.gradient.trainer``) runs, checkpoints and resumes it.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.compare import stats
from jaxtraffic.compare.scenarios import EpisodePool
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.learn.gradient.objective import (
    horizon_steps,
    init_theta,
    make_controller,
    noisy,
    train_pool,
    trainable,
    training_scenarios,
)
from jaxtraffic.learn.gradient.policies import POLICIES
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.sim.metrics import STABLE_STD, density_std
from jaxtraffic.sim.options import Record
from jaxtraffic.sim.rollout import simulate_batch

Array = jax.Array
DIVERGED_COST = 2.0  # a diverged plant costs two stabilised ones
SIGMA_MIN = 0.05  # floor of the search distribution's standard deviation (dimensionless gains)
ELITE_FRACTION = 5  # the elites are the best population / ELITE_FRACTION (rounded, at least 2)
DIVERGED_STD = stats.L2_CAP  # veh/km: the tie-breaker's wave amplitude of a diverged plant (a jam-scale wave)


@struct.dataclass
class CemState:
    """The policy (``theta``: the best parameters evaluated so far, and its ``fitness``), the search
    distribution (``mean``, ``sigma``, same shape as theta), the PRNG key and the generations done (``update``)."""


    theta: Array
    fitness: Array
    mean: Array
    sigma: Array
    key: Array
    update: Array


def fitness(thetas: Array, grad_config: GradientConfig, base: TrafficParams,
            n_steps: int, pool: EpisodePool | None = None, every: int = 0) -> tuple[Array, Array, Array]:
    """(fitness, stabilised count, diverged count), each (P,), of P parameter sets ``thetas`` (P, ...) on the
    training scenarios of ``grad_config`` (module docstring: ``grad_config.cem_fitness`` chooses the fitness;
    ``mean_l2`` samples the L2 norm every ``every`` steps, ``record_every``, static)."""
    scen = training_scenarios(grad_config, base, pool)
    n_p, n_s = thetas.shape[0], scen.rho0.shape[0]
    params = jax.tree.map(lambda x: jnp.tile(x, n_p), scen.params)
    tiled = jnp.repeat(thetas, n_s, axis=0)
    # every (theta, scenario) pair is one environment; each controller is told its plant's delay, and sees its
    # scenario's sensor noise (the same draws for every candidate, as ``compare.tuning`` sees them)
    seen = noisy(grad_config)
    ctrl = jax.vmap(lambda th, d, e: make_controller(th, grad_config, base, d, e if seen else None))(
        tiled, params.delay, jnp.tile(scen.noise, n_p))
    by_l2 = grad_config.cem_fitness == "mean_l2"
    if by_l2 and not every:
        raise ValueError("the mean_l2 fitness needs its recording period: every = record_every(n_steps, dt)")
    res = simulate_batch(params, ctrl, n_steps=n_steps, nominal=base, rho0=jnp.tile(scen.rho0, (n_p, 1)),
                         v0=jnp.tile(scen.v0, (n_p, 1)), batch_controller=True,
                         keys=jnp.tile(scen.keys, (n_p, 1)) if seen else None,
                         record=Record(every=every if by_l2 else 0),
                         metrics=("diverged", "final_rho_L2") if by_l2 else ("diverged",))
    div = res.metrics["diverged"].reshape(n_p, n_s)
    std = density_std(res.final.rho).reshape(n_p, n_s)
    stab = (~div & (std < STABLE_STD)).sum(axis=1)
    n_div = div.sum(axis=1)
    if by_l2:
        tr = res.trajectory
        assert tr is not None  # (recorded)
        t = jnp.append(tr.t[0], n_steps * base.dt)
        l2 = jnp.concatenate([tr.rho_L2, res.metrics["final_rho_L2"][:, None]], axis=1)
        return -stats.capped_mean_l2(t, l2, res.metrics["diverged"]).reshape(n_p, n_s).mean(axis=1), stab, n_div
    tie = jnp.mean(jnp.log(jnp.where(div, DIVERGED_STD, std) + 1e-3), axis=1)
    return stab - DIVERGED_COST * n_div - grad_config.cem_tie_weight * tie, stab, n_div


def record_every(n_steps: int, dt: float) -> int:
    """The recording period in steps of the ``mean_l2`` fitness: ``stats.RECORD_EVERY_S`` (s) in steps of ``dt``
    (s, concrete), lowered to the nearest divisor of ``n_steps`` (the horizon is a whole number of periods)."""
    every = max(1, min(n_steps, round(stats.RECORD_EVERY_S / dt)))
    while n_steps % every:
        every -= 1
    return every


def sample_population(key: Array, mean: Array, sigma: Array, population: int, mask: Array | float = 1.0) -> Array:
    """``population`` parameter sets drawn from the diagonal Gaussian (``mean``, ``sigma``), entries where
    ``mask`` is 0 held at the mean; the first set is the mean itself (its fitness is then known)."""
    noise = jax.random.normal(key, (population, *mean.shape), mean.dtype)
    return (mean + sigma * noise * mask).at[0].set(mean)


def refit(pop: Array, fit: Array) -> tuple[Array, Array, Array]:
    """(index of the fittest set, the new mean, the new sigma): the Gaussian refitted to the elites, the best
    population / ``ELITE_FRACTION`` (at least 2), sigma floored at ``SIGMA_MIN``."""
    order = jnp.argsort(-fit)
    elites = pop[order[:max(2, round(pop.shape[0] / ELITE_FRACTION))]]
    return order[0], elites.mean(axis=0), jnp.maximum(elites.std(axis=0), SIGMA_MIN)


def _generation(state: CemState, grad_config: GradientConfig, base: TrafficParams,
                n_steps: int, pool: EpisodePool | None, every: int) -> tuple[CemState, dict]:
    key, sub = jax.random.split(state.key)
    pop = sample_population(sub, state.mean, state.sigma, grad_config.cem_population,
                            trainable(grad_config, state.mean))
    fit, stab, n_div = fitness(pop, grad_config, base, n_steps, pool, every)
    top, mean, sigma = refit(pop, fit)
    better = fit[top] > state.fitness
    new = CemState(theta=jnp.where(better, pop[top], state.theta), fitness=jnp.where(better, fit[top], state.fitness),
                   mean=mean, sigma=sigma, key=key, update=state.update + 1)
    return new, {"objective": -new.fitness, "grad_norm": jnp.sqrt(jnp.sum(new.sigma**2)),
                 "stabilised": stab[top], "diverged": n_div[top], "mean_stabilised": stab[0],
                 "mean_diverged": n_div[0]}


@functools.partial(jax.jit, static_argnames=("grad_config", "n_steps", "every"))
def _train_chunk(state: CemState, base: TrafficParams, grad_config: GradientConfig,
                 n_steps: int, pool: EpisodePool | None = None, every: int = 0) -> tuple[CemState, dict]:
    return jax.lax.scan(lambda s, _: _generation(s, grad_config, base, n_steps, pool, every), state, None,
                        length=grad_config.steps_per_chunk)


def make_train(grad_config: GradientConfig, base: TrafficParams, devices: list | None = None):
    """``(init, train_chunk)`` as ``objective.make_train``: ``init(key) -> CemState`` (the mean at ``init_theta``,
    sigma ``grad_config.cem_sigma``); ``train_chunk(state) -> (state, metrics)`` runs ``steps_per_chunk`` generations
    in one compiled ``lax.scan``; metrics per generation: objective (-fitness of the policy), grad_norm (the
    norm of sigma: how widely it still searches), the best member's stabilised and diverged counts and the
    mean's. The rollouts are split over this process's devices (``simulate_batch``); ``devices`` is accepted
    for the signature and must be None."""
    if devices is not None or jax.process_count() > 1:
        raise ValueError("the CEM trainer runs in one process, on its devices (devices=None)")
    if "cem" not in POLICIES[grad_config.policy].methods:
        raise ValueError(f"method 'cem' trains the {', '.join(p for p in POLICIES if 'cem' in POLICIES[p].methods)} "
                         f"policy, not {grad_config.policy!r}")
    n_steps = horizon_steps(grad_config, base.dt)
    pool = train_pool(grad_config, base)
    every = record_every(n_steps, float(base.dt)) if grad_config.cem_fitness == "mean_l2" else 0

    def init(key: Array) -> CemState:
        theta = init_theta(grad_config, base, key)
        return CemState(theta=theta, fitness=jnp.asarray(-jnp.inf, theta.dtype), mean=theta,
                        sigma=jnp.full_like(theta, grad_config.cem_sigma), key=key, update=jnp.zeros((), jnp.int32))

    def train_chunk(state: CemState) -> tuple[CemState, dict[str, Any]]:
        return _train_chunk(state, base, grad_config, n_steps, pool, every)

    return init, train_chunk
