"""Oracle rows of the robustness map: how far constant three-gain laws reach, chosen knowing the outcome.

A grid of constant gain triples (eta1, eta2, eta3) of the filtered three-gain law (``control.gain_law``) is
rolled out on every cell of the map (plant delay x plant alpha, the map's horizon, no noise; on the reference
plant through ``control.adapter`` from the paper's grid). Three oracles pick from it with knowledge of the
result (*stabilised*: not diverged and final std_x(rho) < ``STABLE_STD``):

* **best constant**: the one triple that stabilises most cells (ties: fewest diverged);
* **delay schedule**: per plant delay (row), the triple that stabilises most of its cells (ties: fewest
  diverged), i.e. the best law that is told the delay and not alpha, as backstepping and the learned
  delay schedule are;
* **per cell**: a cell counts if any triple stabilises it (a law told both delay and alpha); its value is the
  smallest final std over the triples that did not diverge there.

These bound what a learned gain law of the same class can reach on this gain grid; the rows are written as
JSON (``oracle_json``) and drawn and tabulated beside the controllers' maps (``paper.figures``, REPORT.md).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control import constant_gains
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.control.gain_law import FILTER_SIGMA
from jaxtraffic.paper.learned import STABLE_STD
from jaxtraffic.paper.scenarios import EvalConfig
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM, density_std
from jaxtraffic.sim.rollout import simulate_batch, stack_params

ORACLES = ("best_constant", "delay_schedule", "per_cell")
ORACLE_LABELS = {"best_constant": "oracle: best constant gains", "delay_schedule": "oracle: gains by delay",
                 "per_cell": "oracle: gains per cell"}
# the default gain grid (90 triples): around the laws that stabilise the nominal plant through its filter
DEFAULT_GRID = {"eta1": (-0.4, 0.0, 0.4), "eta2": (-2.0, -1.5, -1.0, -0.5, 0.0),
                "eta3": (-3.0, -2.5, -2.0, -1.5, -1.0, -0.5)}


def gain_grid_map(eval_config: EvalConfig, triples: Sequence[tuple[float, float, float]],
                  filter_sigma: float = FILTER_SIGMA,
                  per_call: int = 4, log: Callable[[str], None] = print) -> tuple[np.ndarray, np.ndarray]:
    """(diverged (T, ND, NA) bool, final std_x(rho) (T, ND, NA) veh/km) of every constant triple on the map of
    ``eval_config`` (its robust delays, alphas and horizon; the law on the paper's grid with filter width
    ``filter_sigma`` m, adapted to ``eval_config``'s plant). ``per_call`` triples share one batched rollout."""
    eval_config = replace(eval_config, horizon_s=eval_config.robust_horizon_s)
    nom = eval_config.nominal()
    dd, aa = np.meshgrid(np.asarray(eval_config.robust_delays), np.asarray(eval_config.robust_alphas), indexing="ij")
    cells = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(dd.ravel(), aa.ravel(), strict=True)]
    rho0, v0 = paper_initial_condition(nom)
    grid = baseline_grid(nom)  # the paper's grid (or a tiny plant's own)
    law = adapt(constant_gains(filter_sigma=filter_sigma, dx=float(nom.L) / (grid.n_points - 1)), grid, nom)
    n_steps = eval_config.n_steps

    @jax.jit
    def run(params, gains):
        b = gains.shape[0]
        res = simulate_batch(params, law.replace(settings=gains), n_steps=n_steps, nominal=nom,
                             rho0=jnp.broadcast_to(rho0, (b, nom.n_points)), v0=jnp.broadcast_to(v0, (b, nom.n_points)),
                             batch_controller=True, metrics=("diverged",))
        return res.metrics["diverged"], density_std(res.final.rho)

    div = np.zeros((len(triples), *dd.shape), bool)
    std = np.zeros((len(triples), *dd.shape))
    t0 = time.perf_counter()
    for lo in range(0, len(triples), per_call):
        part = list(triples[lo:lo + per_call])
        gains = jnp.asarray([g for g in part for _ in cells], jnp.float32)
        d, s = jax.device_get(run(stack_params(*(cells * len(part))), gains))
        div[lo:lo + len(part)] = np.asarray(d, bool).reshape(len(part), *dd.shape)
        std[lo:lo + len(part)] = np.asarray(s, float).reshape(len(part), *dd.shape)
        log(f"  oracle: {lo + len(part)}/{len(triples)} gain triples, {time.perf_counter() - t0:.0f} s")
    return div, std


def _best(stab: np.ndarray, div: np.ndarray) -> int:
    """Index of the candidate (axis 0) with most stabilised cells, ties broken by fewest diverged."""
    s = stab.reshape(stab.shape[0], -1).sum(axis=1)
    d = div.reshape(div.shape[0], -1).sum(axis=1)
    return int(np.lexsort((d, -s))[0])


def oracle_rows(triples: Sequence[tuple[float, float, float]], div: np.ndarray, std: np.ndarray) -> dict[str, dict]:
    """The three oracles of ``gain_grid_map``'s result: name -> {"diverged", "final_rho_spatial_std" (ND, NA),
    "gains": the chosen triple (best constant), one per delay (delay schedule) or None (per cell)}."""
    stab = ~div & (std < STABLE_STD)
    b = _best(stab, div)
    rows = {"best_constant": {"diverged": div[b], "final_rho_spatial_std": std[b], "gains": list(triples[b])}}
    per_delay = [_best(stab[:, i], div[:, i]) for i in range(div.shape[1])]
    rows["delay_schedule"] = {"diverged": np.stack([div[t, i] for i, t in enumerate(per_delay)]),
                              "final_rho_spatial_std": np.stack([std[t, i] for i, t in enumerate(per_delay)]),
                              "gains": [list(triples[t]) for t in per_delay]}
    alive = np.where(div, np.inf, std)
    best_std = alive.min(axis=0)
    rows["per_cell"] = {"diverged": ~np.isfinite(best_std), "final_rho_spatial_std": np.where(
        np.isfinite(best_std), best_std, std.min(axis=0)), "gains": None}
    return rows


def stabilised_and_diverged(row: dict) -> tuple[int, int]:
    """(stabilised cells, diverged cells) of an oracle row or a controller's map."""
    div = np.asarray(row["diverged"], bool)
    return int((~div & (np.asarray(row["final_rho_spatial_std"]) < STABLE_STD)).sum()), int(div.sum())


def grid_triples(eta1: Sequence[float], eta2: Sequence[float], eta3: Sequence[float]) -> list[tuple[float, ...]]:
    return [tuple(float(x) for x in t) for t in itertools.product(eta1, eta2, eta3)]


def oracle_json(eval_config: EvalConfig, triples: Sequence[tuple[float, ...]], rows: dict[str, dict],
                filter_sigma: float,
                extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A JSON-ready record of the oracle rows with the map they were computed on."""
    return {"delays_s": list(map(float, eval_config.robust_delays)), "alphas": list(map(float,
                                                                                        eval_config.robust_alphas)),
            "horizon_s": eval_config.robust_horizon_s, "plant": eval_config.describe(), "filter_sigma_m": filter_sigma,
            "n_gain_triples": len(triples), "stable_std_veh_per_km": STABLE_STD, **(extra or {}),
            "rows": {k: {"diverged": np.asarray(r["diverged"]).tolist(),
                         "final_rho_spatial_std": np.asarray(r["final_rho_spatial_std"]).tolist(),
                         "gains": r["gains"], "stabilised_cells": stabilised_and_diverged(r)[0],
                         "diverged_cells": stabilised_and_diverged(r)[1]} for k, r in rows.items()}}


def load_oracle(path: Path, eval_config: EvalConfig) -> dict[str, dict] | None:
    """The rows of an ``oracle_json`` file if it was computed on ``eval_config``'s map (same delays, alphas and
    horizon), as arrays (std in veh/km: a file of an earlier version, its threshold named ``stable_std_veh_m``,
    held it in veh/m and is converted); None if the file is missing or belongs to another map."""
    import json

    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    same = (np.allclose(data.get("delays_s", []), eval_config.robust_delays) if len(data.get("delays_s", [])) ==
            len(eval_config.robust_delays) else False)
    same = same and len(data.get("alphas", [])) == len(eval_config.robust_alphas) and np.allclose(data["alphas"],
                                                                                        eval_config.robust_alphas)
    if not same or float(data.get("horizon_s", -1)) != float(eval_config.robust_horizon_s):
        return None
    scale = VEH_PER_KM if "stable_std_veh_m" in data else 1.0
    return {k: {"diverged": np.asarray(r["diverged"], bool),
                "final_rho_spatial_std": scale * np.asarray(r["final_rho_spatial_std"], float), "gains": r["gains"]}
            for k, r in data["rows"].items()}
