"""The model-based laws' design parameters tuned on the train split (docs/model.md section 20), with the
optimiser and the budget of the learned residual (``learn.gradient.cem``: the cross-entropy method, a population
of 12 over 10 generations, sigma 0.3 to start).

A ``Tunable`` is a family of laws indexed by a few continuous parameters (backstepping's gain ``k`` and the share
``keep`` of w's damping it keeps; the adaptive law's), each within its bounds, seeing the learned laws' 25 m
measurements. ``tune`` rolls every candidate out on every train scenario (one batched ``simulate_batch`` per
generation, every law told its plant's delay) and ranks candidates by the time-averaged density L2 over the
horizon (``stats.per_scenario``), averaged over the scenarios with a diverged or larger one counted as
``stats.L2_CAP`` veh/km (``stats.capped``): lower is fitter. Scenarios drawn with sensor noise are seen through it
as the comparison sees them (``compare.protocol``: each scenario's level and key), every candidate the same draws.
The result is the fittest parameter set evaluated.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.compare import stats
from jaxtraffic.compare.protocol import measure, steps_of
from jaxtraffic.compare.scenarios import Scenarios
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.control.base import Controller
from jaxtraffic.control.noise import sensor_noise
from jaxtraffic.learn.gradient.cem import refit, sample_population
from jaxtraffic.model.params import TrafficParams


@dataclasses.dataclass(frozen=True)
class Tunable:
    """A family of laws: ``build(delay, *params)`` (arrays of one shape: a batch of laws, each told its delay,
    s) and its parameters' ``names``, ``init``ial values and ``bounds``."""

    name: str
    build: Callable[..., Controller]
    names: tuple[str, ...]
    init: tuple[float, ...]
    bounds: tuple[tuple[float, float], ...]

    def __post_init__(self) -> None:
        if not len(self.names) == len(self.init) == len(self.bounds):
            raise ValueError(f"tunable {self.name}: names, init and bounds must have one entry per parameter")


def _batched(ctrl: Controller, n: int) -> Controller:
    """``ctrl`` with every setting given a leading axis of ``n`` (scalars broadcast)."""
    return ctrl.replace(settings=jax.tree.map(
        lambda x: x if jnp.ndim(x) and jnp.shape(x)[0] == n else jnp.broadcast_to(x, (n, *jnp.shape(x))),
        ctrl.settings))


def fitness(t: Tunable, pop: np.ndarray, scen: Scenarios, nominal: TrafficParams, n_steps: int, every: int
            ) -> np.ndarray:
    """(P,): minus the mean over ``scen`` of each candidate's time-averaged L2 (veh/km, capped at ``stats.L2_CAP``)."""
    n_p, n_s = pop.shape[0], len(scen)
    delays = np.tile(np.asarray(scen.plants.delay, np.float32), n_p)
    params = [np.repeat(pop[:, i].astype(np.float32), n_s) for i in range(pop.shape[1])]
    ctrl = _batched(t.build(delays, *params), n_p * n_s)
    noise = scen.noise_levels()
    noisy = bool(np.any(noise > 0))
    if noisy:  # each scenario's noise as the comparison draws it, the same for every candidate
        ctrl = sensor_noise(ctrl, jnp.asarray(np.tile(noise, n_p), jnp.float32), batched=True)
    ctrl = adapt(ctrl, baseline_grid(nominal), nominal)
    plants = jax.tree.map(lambda x: np.tile(x, n_p) if np.ndim(x) else x, scen.plants)
    per = measure(plants, ctrl, np.tile(scen.rho0, (n_p, 1)), np.tile(scen.v0, (n_p, 1)), nominal, n_steps, every,
                  batch_controller=True, keys=jnp.tile(scen.keys(), (n_p, 1)) if noisy else None)
    return -stats.capped(per["mean_rho_L2"]).reshape(n_p, n_s).mean(axis=1)


def tune(t: Tunable, scen: Scenarios, nominal: TrafficParams, horizon_s: float = 300.0, population: int = 12,
         generations: int = 10, sigma: float = 0.3, seed: int = 0, record_every_s: float = stats.RECORD_EVERY_S,
         log: Callable[[str], None] = print) -> dict[str, Any]:
    """CEM over ``t``'s parameters on ``scen`` (module docstring): the fittest set (``best``, by name), its
    fitness (minus the capped mean time-averaged L2, veh/km) and the generations' history."""
    if scen.split != "train":
        raise ValueError(f"tune on the train split, not {scen.split!r}: the test split is for the comparison")
    dt = float(nominal.dt)
    n_steps, every = steps_of(horizon_s, dt, record_every_s)
    lo, hi = (np.array([b[i] for b in t.bounds], np.float32) for i in (0, 1))
    key = jax.random.key(seed)
    mean, sd = jnp.asarray(t.init, jnp.float32), jnp.full((len(t.init),), sigma, jnp.float32)
    best, best_fit, history = None, -np.inf, []
    for g in range(generations):
        key, sub = jax.random.split(key)
        pop = np.clip(np.asarray(sample_population(sub, mean, sd, population)), lo, hi)
        fit = fitness(t, pop, scen, nominal, n_steps, every)
        top, mean, sd = refit(jnp.asarray(pop), jnp.asarray(fit))
        if best is None or fit[int(top)] > best_fit:
            best, best_fit = pop[int(top)], float(fit[int(top)])
        assert best is not None
        history.append({"generation": g, "best_mean_rho_L2": -best_fit, "mean_of_population": float(-fit.mean())})
        log(f"   {t.name} generation {g + 1}/{generations}: best time-averaged L2 {-best_fit:.3g} veh/km "
            f"({', '.join(f'{n} {v:.3g}' for n, v in zip(t.names, best, strict=True))})")
    if best is None:
        raise ValueError(f"generations must be >= 1, got {generations}")
    return {"best": {n: float(v) for n, v in zip(t.names, best, strict=True)}, "fitness": best_fit,
            "history": history, "budget": {"population": population, "generations": generations,
                                           "scenarios": len(scen), "horizon_s": n_steps * dt}}
