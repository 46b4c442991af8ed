"""Run control laws over a split of scenarios on one plant (docs/model.md section 20).

A law is declared by a ``LawSpec``: its name and label, how it is built (a ``Controller`` on its own grid), what it
is told of each scenario's plant ("nothing", or "delay": ``control.tell_delay`` with the scenario's D) and the grid
it acts on (default: ``baseline_grid``, the paper's whenever the plant refines it). ``evaluate_laws`` runs every law
on every scenario (chunks of ``chunk`` scenarios, one compiled program per law and plant) and returns the
per-scenario measures (``stats.per_scenario``); ``summary_table`` writes their distributions as Markdown. A scenario
drawn with sensor noise has the law see its measurements through ``control.noise.sensor_noise`` at its level, on
the law's own grid (its sensors).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.compare import stats
from jaxtraffic.compare.scenarios import Scenarios
from jaxtraffic.control.adapter import ControllerGrid, adapt, baseline_grid
from jaxtraffic.control.base import Controller, tell_delay
from jaxtraffic.control.noise import sensor_noise
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.sim.options import Record
from jaxtraffic.sim.rollout import simulate_batch

TOLD = ("nothing", "delay", "delay_alpha")
MEASURED = ("diverged", "final_rho_L2", *stats.JS)  # what ``stats.per_scenario`` reads of a rollout


@dataclasses.dataclass(frozen=True)
class LawSpec:
    """A control law in the comparison: ``build()`` gives its ``Controller`` on ``grid`` (None: ``baseline_grid``
    of the plant); ``told``: what it learns of each scenario's plant ("nothing", "delay", or "delay_alpha": D and
    the plant's alpha as its ``alpha0``, the information bound of the adaptive law)."""

    name: str
    label: str
    build: Callable[[], Controller]
    told: str = "nothing"
    grid: ControllerGrid | None = None

    def __post_init__(self) -> None:
        if self.told not in TOLD:
            raise ValueError(f"law {self.name}: told must be one of {TOLD}, got {self.told!r}")


def _slice(tree: Any, i: int, j: int) -> Any:
    return jax.tree.map(lambda x: x[i:j] if np.ndim(x) else x, tree)


def _run(spec: LawSpec, plants: TrafficParams, rho0: np.ndarray, v0: np.ndarray, nominal: TrafficParams,
         n_steps: int, every: int, noise: np.ndarray, keys: jax.Array) -> dict[str, np.ndarray]:
    """One chunk of scenarios under one law: its per-scenario measures. ``noise``: each scenario's sensor noise
    level (``control.noise``; all 0: none, and ``keys`` unused), ``keys``: each scenario's PRNG key."""
    ctrl = spec.build()
    told = spec.told != "nothing"
    if told:
        ctrl = tell_delay(ctrl, jnp.asarray(plants.delay))
    if spec.told == "delay_alpha":
        ctrl = ctrl.replace(settings=ctrl.settings.replace(alpha0=jnp.asarray(plants.alpha, jnp.float32)))
    noisy = bool(np.any(noise > 0))
    if noisy:  # on the law's own grid (its sensors), before the adapter
        ctrl = sensor_noise(ctrl, jnp.asarray(noise, jnp.float32), batched=told)
    ctrl = adapt(ctrl, spec.grid or baseline_grid(nominal), nominal)
    return measure(plants, ctrl, rho0, v0, nominal, n_steps, every, batch_controller=told or noisy,
                   keys=keys if noisy else None)


def steps_of(horizon_s: float, dt: float, record_every_s: float = stats.RECORD_EVERY_S) -> tuple[int, int]:
    """(steps, recording period in steps) of a rollout of at least ``horizon_s`` (s) at time step ``dt`` (s): the
    period ``record_every_s`` (s) in whole steps, the horizon a whole number of periods."""
    every = max(1, round(record_every_s / dt))
    return every * max(1, math.ceil(horizon_s / (every * dt) - 1e-9)), every


def measure(plants: TrafficParams, ctrl: Controller, rho0: Any, v0: Any, nominal: TrafficParams, n_steps: int,
            every: int, batch_controller: bool = False, keys: jax.Array | None = None) -> dict[str, np.ndarray]:
    """The per-scenario measures (``stats.per_scenario``) of one batched rollout of ``ctrl`` (on ``nominal``'s
    grid) on ``plants`` from ``rho0`` (veh/m) and ``v0`` (m/s), (B, n_points) each, over ``n_steps`` steps, the
    density L2 recorded every ``every`` steps and at the end."""
    res = simulate_batch(plants, ctrl, n_steps=n_steps, rho0=jnp.asarray(rho0, jnp.float32),
                         v0=jnp.asarray(v0, jnp.float32), nominal=nominal, batch_controller=batch_controller,
                         keys=keys, record=Record(every=every), metrics=MEASURED)
    tr, met = res.trajectory, {k: np.asarray(v) for k, v in res.metrics.items()}
    assert tr is not None  # (recorded)
    t = np.append(np.asarray(tr.t)[0], n_steps * float(nominal.dt))
    l2 = np.concatenate([np.asarray(tr.rho_L2), met["final_rho_L2"][:, None]], axis=1)
    return stats.per_scenario(t, l2, met["diverged"], met)


def delay_order(scenarios: Scenarios) -> np.ndarray:
    """The scenarios' indices sorted by their plant's delay (stable). A predictor law told each scenario's D runs
    its prediction loop ``round(D / dt)`` steps, and a chunk under ``vmap`` runs its largest D's (``control.
    baselines.predict``): chunks of similar delays skip most of that work. Each scenario's values do not depend on
    its chunk (the masked iterations keep its state), so the order changes the time, not the results."""
    return np.argsort(np.asarray(scenarios.plants.delay, float).reshape(len(scenarios)), kind="stable")


def evaluate_laws(laws: list[LawSpec], scenarios: Scenarios, nominal: TrafficParams, horizon_s: float,
                  record_every_s: float = stats.RECORD_EVERY_S, chunk: int = 64, log: Callable[[str], None] = print,
                  release: bool = True, by_delay: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """Every law of ``laws`` on every scenario (module docstring): name -> per-scenario measures, in the
    scenarios' order. ``nominal``: the model and target every law is handed (the plant's grid, the nominal
    alpha), ``horizon_s`` (s) a whole number of recording periods ``record_every_s`` (s). ``by_delay``: chunk the
    scenarios in the order of their delays (``delay_order``; the same values, in less time). ``release``: drop
    every compiled program after each law (``jax.clear_caches``): each law's programs hold ~300-500 memory
    mappings on the CPU backend, and a long comparison in one process otherwise reaches the kernel's limit
    (``vm.max_map_count``, 65 530) and crashes."""
    n_steps, every = steps_of(horizon_s, float(nominal.dt), record_every_s)
    names = [s.name for s in laws]
    if len(set(names)) != len(names):
        raise ValueError(f"law names must be distinct, got {names}")
    order = delay_order(scenarios) if by_delay else np.arange(len(scenarios))
    plants, rho0, v0 = jax.tree.map(lambda x: x[order] if np.ndim(x) else x, scenarios.plants), \
        scenarios.rho0[order], scenarios.v0[order]
    noise = scenarios.noise_levels()[order]
    keys = scenarios.keys()[order]
    back = np.argsort(order)  # the scenarios' own order again
    out = {}
    for spec in laws:
        t0 = time.perf_counter()
        parts = [_run(spec, _slice(plants, i, i + chunk), rho0[i:i + chunk], v0[i:i + chunk], nominal, n_steps,
                      every, noise[i:i + chunk], keys[i:i + chunk]) for i in range(0, len(scenarios), chunk)]
        out[spec.name] = {k: np.concatenate([p[k] for p in parts])[back] for k in parts[0]}
        if release:
            jax.clear_caches()
        fail, took = out[spec.name]["diverged"].mean(), time.perf_counter() - t0
        log(f"   {spec.label}: median mean L2 {np.median(out[spec.name]['mean_rho_L2']):.3g} veh/km over "
            f"{len(scenarios)} {scenarios.split} scenarios, {100 * fail:.0f} % diverged ({took:.0f} s)")
    return out


def _fmt(x: float, digits: int = 3) -> str:
    return "inf" if not np.isfinite(x) else f"{x:.{digits}g}"


def summary_table(results: dict[str, dict[str, np.ndarray]], labels: dict[str, str], reference: str,
                  seed: int = 0) -> tuple[list[str], dict[str, Any]]:
    """(Markdown lines, the summaries as JSON): per law, the median [95 % interval] of each measure, the failure
    rates, and the ratio of the medians of mean_rho_L2 to ``reference``'s on the same scenarios."""
    summ = {k: stats.summarise(v, results.get(reference), seed) for k, v in results.items()}
    cols = ("mean_rho_L2", "late_max_rho_L2", "settle_s", "J_comfort")
    head = ["law", *(f"{c} ({stats.UNITS[c]})" for c in cols),
            f"median mean_rho_L2 / {labels.get(reference, reference)}'s", "diverged", "not settled"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k, s in summ.items():
        cells = [labels.get(k, k)]
        for c in cols:
            lo, hi = s[c]["ci95"]
            cells.append(f"{_fmt(s[c]['median'])} [{_fmt(lo)}, {_fmt(hi)}]")
        r = s["ratio_mean_rho_L2"]
        cells.append(f"{_fmt(r['value'])} [{_fmt(r['ci95'][0])}, {_fmt(r['ci95'][1])}]")
        for f in ("diverged_rate", "not_settled_rate"):
            cells.append(f"{100 * s[f]['value']:.0f} % [{100 * s[f]['ci95'][0]:.0f}, {100 * s[f]['ci95'][1]:.0f}]")
        lines.append("| " + " | ".join(cells) + " |")
    return lines, summ
