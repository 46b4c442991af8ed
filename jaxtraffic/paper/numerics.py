"""Numerical uncertainty of Table 2: the D = 4 s scenario on a refined grid and with the
other scheme, and the relative change of every index.

Every controller acts on its own grid (the baselines on the paper's, ``control.adapter.baseline_grid``;
a learned policy on its training grid, ``runs.policy.policy_grid``) through ``control.adapter``:
only the plant is refined (twice the points and twice the solver steps, so the CFL bound stays) or
changes scheme.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from jaxtraffic.control import Controller
from jaxtraffic.control.adapter import ControllerGrid, adapt, baseline_grid
from jaxtraffic.paper.scenarios import CTRL_DELAY, EXTRA_LEARNED, EvalConfig, others, run_batch
from jaxtraffic.sim.units import INDEX_UNITS

NUMERICS_CONTROLLERS = ("open_loop", "backstepping", "ppo", *EXTRA_LEARNED)
NUMERICS_INDICES = ("J_TTT", "J_fuel", "J_comfort", "J_comfort_a2", "J_comfort_at2", "J_comfort_no_switch_on",
                    "J_TTT_kmh", "J_fuel_kmh", "J_comfort_kmh", "J_comfort_no_switch_on_kmh", "J_comfort_switch_on",
                    "final_rho_L2", "final_v_L2")


def deploy(controllers: dict[str, Controller], grids: dict[str, ControllerGrid], eval_config: EvalConfig
           ) -> dict[str, Controller]:
    """Each controller adapted to the plant of ``eval_config`` from its own grid (``grids``; absent: a baseline,
    on ``baseline_grid``)."""
    nom = eval_config.nominal()
    return {k: adapt(c, grids.get(k) or baseline_grid(nom), nom) for k, c in controllers.items()}


def variants(eval_config: EvalConfig) -> dict[str, EvalConfig]:
    """The two numerical variants of ``eval_config``'s plant: refined twice (points and solver steps), and its
    other scheme."""
    other = "muscl" if eval_config.scheme == "upwind" else "upwind"
    return {"refined": replace(eval_config, n_points=2 * eval_config.n_points - 1, substeps=2 * eval_config.substeps),
            "scheme": replace(eval_config, scheme=other)}


def describe(eval_config: EvalConfig) -> dict[str, Any]:
    nom = eval_config.nominal()
    return {"scheme": eval_config.scheme, "n_points": eval_config.n_points, "dx_m": float(nom.dx),
            "dt_s": eval_config.dt,
            "substeps": eval_config.substeps}


def _rel(a: float, b: float) -> float | None:
    """(a - b) / |b|, None if b is 0 or either is not finite."""
    if not (np.isfinite(a) and np.isfinite(b)) or b == 0:
        return None
    return float((a - b) / abs(b))


def run_numerics(controllers: dict[str, Controller], grids: dict[str, ControllerGrid], eval_config: EvalConfig,
                 log: Callable[[str], None] = print) -> dict[str, Any]:
    """Scenario delay4 for ``NUMERICS_CONTROLLERS`` (and any ``others``) under each of ``variants(eval_config)``.

    ``controllers``: on their own grids (``grids``; baselines absent, see ``deploy``). Independent of the
    evaluation on ``eval_config`` itself, so it can run alongside it; ``relative_to`` then adds the differences to it.
    Returns {"base": description, "variants": {name: description}, "delay4": {variant: {controller:
    {index: value}}}}.
    """
    out: dict[str, Any] = {"base": describe(eval_config), "variants": {}, "delay4": {},
                           "note": "rel_diff = (J_variant - J) / |J|; every controller acts on its own grid "
                                   "(control.adapter), only the plant changes"}
    for vname, vcfg in variants(eval_config).items():
        out["variants"][vname] = describe(vcfg)
        out["delay4"][vname] = {}
        nom = vcfg.nominal(delay=CTRL_DELAY)
        chosen = {c: controllers[c] for c in (*NUMERICS_CONTROLLERS, *others(controllers)) if c in controllers}
        for c, ctrl in deploy(chosen, grids, vcfg).items():
            res = run_batch(ctrl, [nom], [0], vcfg, record=False)
            out["delay4"][vname][c] = {k: float(np.asarray(res.metrics[k])[0]) for k in NUMERICS_INDICES}
        log(f"  numerics {vname:<8s} ({vcfg.describe()}): "
            + ", ".join(f"{c} J_comfort {v['J_comfort']:.4g}" for c, v in out["delay4"][vname].items())
            + f" ({INDEX_UNITS['J_comfort']})")
    return out


def relative_to(numerics: dict[str, Any], base: dict[str, dict[str, float]]) -> dict[str, Any]:
    """``run_numerics``' output with "rel_diff" = {variant: {controller: {index: (variant - base) /
    |base|}}} against ``base``, metrics.json's delay4 entries on the base grid (controllers absent
    from ``base`` are dropped)."""
    delay4 = {v: {c: vals for c, vals in per.items() if c in base} for v, per in numerics["delay4"].items()}
    rel = {v: {c: {k: _rel(vals[k], base[c][k]) for k in NUMERICS_INDICES if k in base[c]} for c, vals in per.items()}
           for v, per in delay4.items()}
    return {**numerics, "delay4": delay4, "rel_diff": rel}


def survives(numerics: dict[str, Any], metrics: dict, eval_config: EvalConfig) -> list[tuple[str, dict[str, bool]]]:
    """Which of the Table 2 conclusions hold on the base grid and under each variant:
    (conclusion, {"base": bool, variant: bool, ...})."""
    from jaxtraffic.paper.summaries import equilibrium_indices

    eq = equilibrium_indices(eval_config)
    tables = {"base": {c: metrics["delay4"][c] for c in (*NUMERICS_CONTROLLERS, *others(metrics["delay4"]))
                       if c in metrics["delay4"]}}
    tables.update(numerics.get("delay4", {}))
    checks: list[tuple[str, Callable[[dict], bool]]] = [
        ("open loop worse than backstepping and PPO on J_TTT, J_fuel, J_comfort",
         lambda t: all(t["open_loop"][i] > max(t["backstepping"][i], t["ppo"][i])
                       for i in ("J_TTT", "J_fuel", "J_comfort"))),
        ("backstepping and PPO J_TTT, J_fuel within 3 % of the equilibrium values",
         lambda t: all(abs(t[c][i] - eq[i]) <= 0.03 * eq[i] for c in ("backstepping", "ppo")
                       for i in ("J_TTT", "J_fuel"))),
        ("PPO less comfortable than backstepping (J_comfort)",
         lambda t: t["ppo"]["J_comfort"] > t["backstepping"]["J_comfort"]),
        ("PPO less comfortable than backstepping without the switch-on step",
         lambda t: t["ppo"]["J_comfort_no_switch_on"] > t["backstepping"]["J_comfort_no_switch_on"]),
        ("fuel improvement below the TTT improvement (km/h reading), as in the paper",
         lambda t: all(_impr(t, c, "J_fuel_kmh") < _impr(t, c, "J_TTT") for c in ("backstepping", "ppo"))),
    ]
    rows = []
    for text, fn in checks:
        res = {}
        for name, t in tables.items():
            try:
                res[name] = bool(fn(t))
            except (KeyError, TypeError):
                continue
        rows.append((text, res))
    return rows


def _impr(t: dict, c: str, idx: str) -> float:
    return (t["open_loop"][idx] - t[c][idx]) / t["open_loop"][idx]

