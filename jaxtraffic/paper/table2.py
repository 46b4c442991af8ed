"""Table 2 (D = 4 s, first 300 s) in both readings of the indices, with the paper's values next to
the reading that matches them, and the numerical uncertainty of every number (``paper.numerics``)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from jaxtraffic.paper.scenarios import EvalConfig
from jaxtraffic.paper.summaries import (
    INDICES,
    PAPER_IMPROVEMENT,
    PAPER_TABLE2,
    TABLE_CONTROLLERS,
    _fmt,
    _fmt_paper,
    equilibrium_indices,
    improvement,
)
from jaxtraffic.sim.units import INDEX_UNITS, labelled

READINGS = {"SI": "", "km/h": "_kmh"}  # reading -> suffix of the metrics.json key


def matching_reading(values: dict[str, float | None], paper: float) -> str:
    """The reading whose value is closest to the paper's in |log ratio| ("both" on a tie)."""
    dist = {r: abs(math.log(v / paper)) for r, v in values.items() if v is not None and v > 0}
    if not dist:
        return "n/a"
    best = min(dist.values())
    close = [r for r, d in dist.items() if d <= best + 1e-12]
    return "both" if len(close) > 1 else close[0]


def rounds_to_paper(x: float | None, paper: float) -> bool:
    return x is not None and float(f"{x:.1e}") == paper


def _rel(numerics: dict | None, variant: str, c: str, key: str) -> float | None:
    if not numerics:
        return None
    return numerics.get("rel_diff", {}).get(variant, {}).get(c, {}).get(key)


def _variant_improvement(numerics: dict | None, variant: str, c: str, key: str) -> float | None:
    if not numerics:
        return None
    t = numerics.get("delay4", {}).get(variant, {})
    if c not in t or "open_loop" not in t or key not in t[c]:
        return None
    return improvement(t["open_loop"][key], t[c][key])


def table2_rows(metrics: dict, eval_config: EvalConfig, numerics: dict | None = None) -> list[dict[str, Any]]:
    """One row per (index, controller) at D = 4 s: the value and improvement in each reading, the
    paper's, the matching reading, and the relative change under each numerical variant."""
    d4 = metrics["delay4"]
    eq = equilibrium_indices(eval_config)
    rows = []
    for idx in INDICES:
        for c in TABLE_CONTROLLERS:
            e = d4.get(c, {})
            row: dict[str, Any] = {"index": idx, "controller": c}
            vals = {}
            for r, suf in READINGS.items():
                key = idx + suf
                vals[r] = e.get(key)
                row[f"ours_{r}"] = e.get(key)
                row[f"equilibrium_{r}"] = eq.get(key) if idx != "J_comfort" else None
                if c != "open_loop":
                    row[f"improvement_pct_{r}"] = improvement(d4.get("open_loop", {}).get(key), e.get(key))
                for v in ("refined", "scheme"):
                    row[f"rel_diff_{v}_{r}"] = _rel(numerics, v, c, key)
                    if c != "open_loop":
                        ours_v = _variant_improvement(numerics, v, c, key)
                        base = row[f"improvement_pct_{r}"]
                        row[f"improvement_change_{v}_{r}"] = (None if ours_v is None or base is None
                                                              else ours_v - base)
            row["paper"] = PAPER_TABLE2[idx][c]
            row["improvement_pct_paper"] = PAPER_IMPROVEMENT[idx].get(c)
            row["matching_reading"] = matching_reading(vals, row["paper"])
            row["rounds_to_paper"] = {r: rounds_to_paper(v, row["paper"]) for r, v in vals.items()}
            rows.append(row)
    return rows


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:+.2f} %"


def _pts(x: float | None) -> str:
    return "n/a" if x is None else f"{x:+.2f}"


def write_table2(rows: list[dict[str, Any]], out_dir: Path, horizon_s: float, metrics: dict | None = None,
                 numerics: dict | None = None) -> None:
    """table2.csv (all columns) and table2.md: values, improvements, the comfort split."""
    cols = [k for k in rows[0] if k != "rounds_to_paper"]
    with open(out_dir / "table2.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    var = ""
    if numerics:
        vs = numerics["variants"]
        var = (f" Delta refined = relative change on the grid refined twice ({vs['refined']['n_points']} points, "
               f"dx = {vs['refined']['dx_m']:g} m, {vs['refined']['scheme']}); Delta scheme = relative change with "
               f"the {vs['scheme']['scheme']} scheme on the same grid.")
    lines = [
        f"# Table 2: performance indices, plant delay D = 4 s, first {horizon_s:g} s",
        "",
        "Two readings of the integrands (docs/model.md section 10): **SI** (speeds in m/s, the library's own) "
        "and **km/h** (the paper's: speeds in km/h inside the integrands, a in km/h/s, xi(3.6 v, 3.6 a)); rho in "
        "veh/km, x in m, t in s in both. Units (SI): " + ", ".join(labelled(k) for k in INDEX_UNITS)
        + " (J_TTT / 1000 is the total travel time in veh·s; the km/h reading's J_fuel and J_comfort put km/h "
        "for m/s). **Paper** = Table 2 as printed (2 significant digits), next to the "
        "reading closest to it (matching reading)." + var + " Improvement = (J_open_loop - J) / J_open_loop.",
        "",
        "| index | controller | SI | Delta refined | Delta scheme | km/h | Delta refined | Delta scheme "
        "| **paper** | matching reading | rounds to paper (SI / km/h) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rp = r["rounds_to_paper"]
        lines.append(
            f"| {r['index']} | {r['controller']} | {_fmt(r['ours_SI'])} | {_pct(r['rel_diff_refined_SI'])} "
            f"| {_pct(r['rel_diff_scheme_SI'])} | {_fmt(r['ours_km/h'])} | {_pct(r['rel_diff_refined_km/h'])} "
            f"| {_pct(r['rel_diff_scheme_km/h'])} | {_fmt_paper(r['paper'])} | {r['matching_reading']} "
            f"| {'yes' if rp['SI'] else 'no'} / {'yes' if rp['km/h'] else 'no'} |")
    lines += ["", "Improvements over the open loop (change under each variant in percentage points):", "",
              "| index | controller | SI | Delta refined | Delta scheme | km/h | Delta refined | Delta scheme "
              "| **paper** |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["controller"] == "open_loop":
            continue
        lines.append(
            f"| {r['index']} | {r['controller']} | {_fmt(r['improvement_pct_SI'], True)} "
            f"| {_pts(r['improvement_change_refined_SI'])} | {_pts(r['improvement_change_scheme_SI'])} "
            f"| {_fmt(r['improvement_pct_km/h'], True)} | {_pts(r['improvement_change_refined_km/h'])} "
            f"| {_pts(r['improvement_change_scheme_km/h'])} | {_fmt_paper(r['improvement_pct_paper'], True)} |")
    if metrics is not None:
        lines += comfort_split_lines(metrics, numerics)
    (out_dir / "table2.md").write_text("\n".join(lines) + "\n")


def comfort_split_lines(metrics: dict, numerics: dict | None = None) -> list[str]:
    """J_comfort at D = 4 s as its a^2 and a_t^2 parts, the switch-on step, and without it."""
    d4 = metrics["delay4"]
    lines = ["", "Comfort split (SI; the km/h values are 3.6^2 = 12.96 times these). The switch-on step is "
             "n = D/dt, when the first controlled input reaches the plant; its a_t^2 is a single spike that "
             "grows like 1/dt. 'without switch-on' drops that one step's a_t^2 for every controller "
             "(at D = 0 it is 0 by the a^{-1} := a^0 rule).", "",
             "| controller | J_comfort | a^2 part | a_t^2 part | switch-on step | without switch-on "
             "| without switch-on, Delta refined | km/h without switch-on | improvement without switch-on |",
             "|---|---|---|---|---|---|---|---|---|"]
    ol = d4.get("open_loop", {}).get("J_comfort_no_switch_on")
    for c in ("open_loop", "lyapunov", "backstepping", "ppo"):
        e = d4.get(c)
        if not e or "J_comfort_a2" not in e:
            continue
        imp = "" if c == "open_loop" else _fmt(improvement(ol, e["J_comfort_no_switch_on"]), True)
        lines.append(f"| {c} | {_fmt(e['J_comfort'])} | {_fmt(e['J_comfort_a2'])} | {_fmt(e['J_comfort_at2'])} "
                     f"| {_fmt(e['J_comfort_switch_on'])} | {_fmt(e['J_comfort_no_switch_on'])} "
                     f"| {_pct(_rel(numerics, 'refined', c, 'J_comfort_no_switch_on'))} "
                     f"| {_fmt(e['J_comfort_no_switch_on_kmh'])} | {imp} |")
    return lines
