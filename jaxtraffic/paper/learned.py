"""Beyond the paper: the learned controllers side by side (PPO and gradient-based training).

``comparison_section`` writes REPORT.md's section comparing how each learned controller was
obtained (algorithm, wall time, environment steps) with what it achieves (Table 2 quality at
D = 4 s, plant delays 0-6 s, the robustness map), every number read from the runs' summary.json
and the evaluation's own metrics.

Stabilised cell of the robustness map: not diverged and the final spatial standard deviation of
the density below ``STABLE_STD`` (0.5 veh/km), i.e. the waves are gone (a steady offset from the
nominal target, which a plant with another alpha keeps, is allowed).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jaxtraffic.paper import laws
from jaxtraffic.paper.maps import judge_key, judge_label
from jaxtraffic.sim.metrics import STABLE_STD
from jaxtraffic.sim.units import INDEX_UNITS, labelled


def stabilised_cells(r: dict[str, np.ndarray]) -> int:
    """Cells of one controller's robustness map that are stabilised (see the module docstring)."""
    return int(np.sum(~np.asarray(r["diverged"], bool) & (np.asarray(r["final_rho_spatial_std"]) < STABLE_STD)))


def seconds_to_beat(curve: dict[str, np.ndarray] | None, rho_l2: float, j_comfort: float) -> float | None:
    """Wall time of the first learning-curve row whose evaluation beats (``rho_l2`` veh/km,
    ``j_comfort``) on both final density L2 and J_comfort; None if none does."""
    if not curve:
        return None
    l2 = curve.get("eval_rho_L2_veh_km", curve.get("eval_rho_L2"))
    if l2 is None or "eval_J_comfort" not in curve or "wall_s" not in curve:
        return None
    hit = np.flatnonzero((np.asarray(l2) < rho_l2) & (np.asarray(curve["eval_J_comfort"]) < j_comfort))
    return float(curve["wall_s"][hit[0]]) if hit.size else None


def _num(x: Any, fmt: str) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def _map_cell(table: dict[str, Any], name: str) -> str:
    """"s/n (told ...)": the controllable cells of ``table``'s row ``name`` that stay stabilised
    (``maps.judge_key``: at the map's horizon for a table without the late maximum)."""
    r = table["rows"][name]
    return f"{r[judge_key(table)]}/{table['controllable']} (told {r['told']})"


def comparison_section(metrics: dict, runs: dict[str, dict], robust: dict[str, dict[str, np.ndarray]],
                       alphas: tuple[float, ...], delays: tuple[float, ...], horizon_s: float,
                       table: dict[str, Any] | None = None) -> list[str]:
    """Markdown lines of the section. ``runs``: controller name -> {"summary": summary.json of its
    run, "curve": its learning curve (column -> array) or None, "run_dir": ...} for every learned
    controller evaluated. ``horizon_s``: the evaluation's simulated time, s. ``table``: the map's counts by
    what each controller is told (``paper.maps.map_table``): the map column then counts the controllable
    cells, says what each is told, and the model-based rows (backstepping, adaptive backstepping, told alpha)
    close the table."""
    if not runs:
        return []
    d4 = metrics["delay4"]
    bs = d4.get("backstepping", {})
    j = [i for i, a in enumerate(alphas) if abs(a - 0.15) < 1e-9]
    lines = ["## Beyond the paper: PPO and gradient-based training", "",
             "Every learned controller acts through the paper's three-gain law. PPO learns from sampled "
             "episodes; the gradient-based controllers are trained by differentiating the rollout objective "
             "through the simulator (`jaxtraffic.learn.gradient.objective`). Training figures come from each run's "
             "summary.json and learning curve (wall time includes compilation, on the machine that trained it; "
             "*s to beat backstepping*: first evaluation during training whose final rho L2 and J_comfort are both "
             "below backstepping's); quality figures "
             f"from this evaluation (paper initial condition, D = 4 s, {horizon_s:g} s, backstepping for reference: "
             f"final rho L2 {_num(bs['final_rho_L2'], '.3f') if bs else 'n/a'} veh/km, J_comfort "
             f"{_num(bs.get('J_comfort'), '.4g')} {INDEX_UNITS['J_comfort']}). *Map* = cells of the robustness map "
             f"{judge_label(table) if table else 'stabilised at its horizon'} (not diverged, std_x(rho) < "
             f"{STABLE_STD:g} veh/km; of the controllable cells, and what each "
             "controller is told, when the map's table is given); *delays* = plant delays of the map "
             "at alpha = 0.15 where it is stabilised.", "",
             "| controller | run | training wall s | env steps | s to beat backstepping | final rho L2 (veh/km) "
             f"| {labelled('J_comfort')} | J_comfort / backstepping | map | delays (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, run in runs.items():
        s, m = run["summary"], d4.get(name, {})
        r = robust.get(name)
        cells, ok_delays = "n/a", "n/a"
        if r is not None:
            cells = f"{stabilised_cells(r)}/{np.asarray(r['diverged']).size}"
            if table and name in table["rows"]:
                cells = _map_cell(table, name)
            if j:
                col = ~np.asarray(r["diverged"], bool)[:, j[0]] & (np.asarray(r["final_rho_spatial_std"])[:, j[0]]
                                                                   < STABLE_STD)
                ok = [d for d, k in zip(delays, col, strict=True) if k]
                ok_delays = "none" if not ok else (f"{min(ok):g}-{max(ok):g}" if len(ok) == len(delays)
                                                   else ", ".join(f"{d:g}" for d in ok))
        ratio = m.get("J_comfort") / bs["J_comfort"] if m.get("J_comfort") is not None and bs else None
        t_beat = seconds_to_beat(run.get("curve"), bs["final_rho_L2"], bs["J_comfort"]) if bs else None
        lines.append(
            f"| {laws.label(name)} | `{run['run_dir']}` | {_num(s.get('wall_s'), '.1f')} "
            f"| {_num(s.get('env_steps'), '.3g')} | {_num(t_beat, '.1f')} "
            f"| {_num(m['final_rho_L2'] if m else None, '.3f')} | {_num(m.get('J_comfort'), '.4g')} "
            f"| {_num(ratio, '.2f')} | {cells} | {ok_delays} |")
    if table:
        for name, label in (("backstepping", "backstepping"), ("adaptive_backstepping", "adaptive backstepping"),
                            ("backstepping_alpha", "backstepping told alpha (information bound)")):
            if name in table["rows"]:
                lines.append(f"| {label} | | | | | | | | {_map_cell(table, name)} | |")
    elif "backstepping" in robust:
        lines.append(f"| backstepping (assumes the true delay) | | | | | | | | "
                     f"{stabilised_cells(robust['backstepping'])}/{np.asarray(robust['backstepping']['diverged']).size}"
                     " | |")
    return lines + [""]
