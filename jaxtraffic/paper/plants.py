"""The paper's experiments on two plants side by side: the paper's grid and the reference plant.

``compare_plants`` reads what ``evaluate_all`` wrote for each plant (metrics.json, robustness.json)
and writes ``plants.md`` / ``plants.json`` (claim by claim: which conclusions hold on each plant;
Table 2's scenario and the learned controllers against backstepping on each; the robustness maps;
the numerical check of each plant) and ``fig_plants_delay4.png``, and appends the same section to
the first plant's REPORT.md. Every controller acts on its own grid on both plants (``control.adapter``),
so a difference between the two columns is a property of the plant's discretisation.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxtraffic.io.drawing import new_figure, save_figure
from jaxtraffic.io.files import atomic_write_text, write_json
from jaxtraffic.paper import laws
from jaxtraffic.paper.learned import STABLE_STD
from jaxtraffic.paper.maps import excluded_text, judge_key, judge_label, rejudge
from jaxtraffic.paper.scenarios import EXTRA_LEARNED, EvalConfig, learned, others
from jaxtraffic.paper.summaries import _fmt
from jaxtraffic.sim.units import INDEX_UNITS, labelled

CLAIMS = {1: "learning curve; PPO converges, the open loop does not", 2: "D = 0: PPO vs Lyapunov",
          3: "D = 4 s: Lyapunov fails, backstepping and PPO stabilise", 4: "Table 2 (300 s, D = 4 s)",
          5: "alpha noise: PPO stabilises, backstepping fails", 6: "mismatched delay 3 s / 5 s"}
DELAY4 = ("open_loop", "lyapunov", "backstepping", "ppo", *EXTRA_LEARNED)
TITLE = "## The experiments on the reference plant"


def _out_dir(root: Path, plant: str, first: str) -> Path:
    return root if plant == first else root / plant


def _map_counts(robust: dict[str, Any]) -> dict[str, tuple[int, int, int]]:
    """controller -> (stabilised cells, diverged cells, all cells) of a robustness.json."""
    out = {}
    for name, r in robust.get("controllers", {}).items():
        div = np.asarray(r["diverged"], bool)
        std = np.asarray(r["final_rho_spatial_std"], float)
        out[name] = (int(np.sum(~div & (std < STABLE_STD))), int(div.sum()), int(div.size))
    return out


def plant_table(results: dict[str, dict], configs: dict[str, EvalConfig]) -> dict[str, Any]:
    """The machine-readable comparison (``plants.json``)."""
    d4 = {p: {c: {k: m["delay4"][c].get(k) for k in ("J_TTT", "J_fuel", "J_comfort", "J_comfort_no_switch_on",
                                                      "J_comfort_a2", "final_rho_L2", "diverged")}
              for c in (*DELAY4, *others(m["delay4"])) if c in m["delay4"]} for p, m in results.items()}
    return {"plants": {p: {"description": configs[p].describe(), "n_points": configs[p].n_points,
                           "scheme": configs[p].scheme, "substeps": configs[p].substeps, "dt_s": configs[p].dt}
                       for p in results},
            "claims": {p: m["meta"]["claims"] for p, m in results.items()},
            "delay4": d4,
            "numerics_rel_diff": {p: m.get("numerics", {}).get("rel_diff") for p, m in results.items()}}


def _claims_lines(table: dict[str, Any], plants: list[str]) -> list[str]:
    lines = ["| claim | " + " | ".join(plants) + " |", "|---|" + "---|" * len(plants)]
    for cid, text in CLAIMS.items():
        cells = [table["claims"][p].get(str(cid), "n/a") for p in plants]
        changed = len(set(cells)) > 1
        lines.append(f"| {cid}. {text} | " + " | ".join(f"**{c}**" if changed else c for c in cells) + " |")
    return lines


def _delay4_lines(table: dict[str, Any], plants: list[str], horizon_s: float) -> list[str]:
    lines = ["| controller | " + " | ".join(f"rho L2 {horizon_s:g} s (veh/km), {p}" for p in plants) + " | "
             + " | ".join(f"{labelled('J_comfort')}, {p}" for p in plants)
             + " | vs backstepping (L2, J_comfort) on each |",
             "|---|" + "---|" * (2 * len(plants) + 1)]
    for c in (*DELAY4, *others(next(iter(table["delay4"].values())))):
        if not all(c in table["delay4"][p] for p in plants):
            continue
        e = [table["delay4"][p][c] for p in plants]
        rel = []
        for p in plants:
            bs, me = table["delay4"][p].get("backstepping"), table["delay4"][p][c]
            if bs and c != "backstepping" and bs["final_rho_L2"] and bs["J_comfort"]:
                l2, jc = me["final_rho_L2"] / bs["final_rho_L2"], me["J_comfort"] / bs["J_comfort"]
                rel.append(f"{p}: {l2:.2f}x, {jc:.2f}x")
        lines.append(f"| {laws.label(c)} | " + " | ".join(_fmt(x["final_rho_L2"]) for x in e) + " | "
                     + " | ".join(_fmt(x["J_comfort"]) + (" (diverged)" if x["diverged"] else "") for x in e)
                     + f" | {'; '.join(rel) or '-'} |")
    return lines


def _numerics_lines(table: dict[str, Any], plants: list[str], results: dict[str, dict], horizon_s: float) -> list[str]:
    lines = ["Each plant's own numerical check (Table 2's scenario on the plant refined twice, points and solver "
             f"steps, and with the other scheme; relative change of the density L2 at {horizon_s:g} s and J_comfort):",
             "",
             "| plant | controller | refined: L2 | refined: J_comfort | other scheme: L2 | other scheme: J_comfort |",
             "|---|---|---|---|---|---|"]
    for p in plants:
        rel = table["numerics_rel_diff"].get(p) or {}
        for c in ("backstepping", *learned(rel.get("refined", {}))):
            if c not in rel.get("refined", {}):
                continue
            cells = [rel[v][c].get(k) for v in ("refined", "scheme") for k in ("final_rho_L2", "J_comfort")]
            lines.append(f"| {p} | {laws.label(c)} | "
                         + " | ".join("n/a" if x is None else f"{100 * x:+.1f} %" for x in cells) + " |")
    refined = {p: results[p].get("numerics", {}).get("variants", {}).get("refined", {}) for p in plants}
    lines += ["", "Refined plants: " + "; ".join(f"{p}: {r.get('n_points')} points, {r.get('substeps')} solver steps"
                                                 for p, r in refined.items() if r) + "."]
    return lines


def _map_lines(robust: dict[str, dict], plants: list[str]) -> list[str]:
    """Markdown: per controller, what it is told and its stabilised / diverged counts on each plant's map, over
    the controllable cells (robustness.json's "table", ``paper.maps``; an older file without it: over all
    cells), then the excluded cells of each plant. Stabilised: the cells that stay stabilised where the table
    has them (``maps.judge_key``), else at the map's horizon."""
    tables = {p: robust[p].get("table") or {} for p in plants}
    counts = {p: ({c: (r[judge_key(tables[p])], r["diverged"], tables[p]["controllable"])
                   for c, r in tables[p]["rows"].items()} if tables[p].get("rows") else _map_counts(robust[p]))
              for p in plants}
    told = {c: r.get("told", "n/a") for p in reversed(plants) for c, r in tables[p].get("rows", {}).items()}
    names = [c for c in counts[plants[0]] if all(c in counts[p] for p in plants)]
    what = {p: judge_label(tables[p]) if tables[p].get("rows") else "stabilised" for p in plants}
    lines = ["| controller | told | " + " | ".join(f"{p}: {what[p]} / diverged of controllable cells" for p in plants)
             + " |", "|---|---|" + "---|" * len(plants)]
    for c in names:
        lines.append(f"| {laws.label(c)} | {told.get(c, 'n/a')} | "
                     + " | ".join(f"{counts[p][c][0]} / {counts[p][c][1]} of {counts[p][c][2]}" for p in plants) + " |")
    lines.append("")
    lines += [f"- {p}: {excluded_text(tables[p])}" for p in plants if tables[p].get("rows")]
    for p in plants:
        if tables[p].get("rows"):
            r = rejudge(tables[p])
            lines.append(f"- {p}: claim 5 re-judged on this map: **{r['verdict']}** ({r['text']})")
    return lines


def plot_plants(png: Path, table: dict[str, Any], plants: list[str], horizon_s: float) -> None:
    """Bars: density L2 at ``horizon_s`` (s) and J_comfort at D = 4 s, per controller, one colour per plant (log
    axes)."""
    names = [c for c in (*DELAY4, *others(table["delay4"][plants[0]])) if c != "open_loop"
             and all(c in table["delay4"][p] for p in plants)]
    fig = new_figure(figsize=(11, 3.8))
    axes = fig.subplots(1, 2)
    width = 0.8 / len(plants)
    for ax, key, label in ((axes[0], "final_rho_L2", f"density L2 at {horizon_s:g} s (veh/km)"),
                           (axes[1], "J_comfort", f"J_comfort over {horizon_s:g} s\n({INDEX_UNITS['J_comfort']})")):
        for i, p in enumerate(plants):
            vals = [table["delay4"][p][c][key] for c in names]
            ax.bar(np.arange(len(names)) + i * width, vals, width, label=p)
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(names)) + width * (len(plants) - 1) / 2)
        ax.set_xticklabels([laws.label(c).replace("gradient: ", "grad. ") for c in names], rotation=20,
                           fontsize=8)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(title="plant")
    fig.suptitle("D = 4 s, the paper's initial condition: the same controllers on the two plants")
    save_figure(fig, png)


def compare_plants(results: dict[str, dict], configs: dict[str, EvalConfig], out_dir: str | Path,
                   log: Callable[[str], None] = print) -> tuple[dict[str, Any], str]:
    """Write plants.md, plants.json and fig_plants_delay4.png into ``out_dir`` (the first plant's output
    directory; the others' are its subdirectories named after them); return the table and plants.md's text (a
    section of the first plant's REPORT.md, ``paper.job``)."""
    out_dir = Path(out_dir)
    plants = list(results)
    first = plants[0]
    table = plant_table(results, configs)
    robust = {p: json.loads((_out_dir(out_dir, p, first) / "robustness.json").read_text()) for p in plants}
    horizon_s = configs[first].horizon_s  # (every plant's evaluation runs the same time)
    plot_plants(out_dir / "fig_plants_delay4.png", table, plants, horizon_s)
    lines = [TITLE, "",
             "Every experiment ran on " + " and ".join(f"the **{p}** plant ({configs[p].describe()})" for p in plants)
             + ". Every controller acts on its own grid on both (the baselines on the paper's 5 m grid at 0.1 s, "
             "a learned one on its training grid; `control.adapter`), so a difference between the columns is the "
             "plant's discretisation, not the controller's. The reference plant is where the results no longer "
             "depend on the grid (docs/model.md section 15).", "",
             "### Claim by claim", "", *_claims_lines(table, plants), "",
             "### D = 4 s (Table 2's scenario)", "", *_delay4_lines(table, plants, horizon_s), "",
             "![plants](fig_plants_delay4.png)", "",
             "| " + " | ".join(plants) + " |", "|" + "---|" * len(plants),
             "| " + " | ".join(f"![{p}]({'' if p == first else p + '/'}fig6_l2_delay4.png)" for p in plants) + " |",
             "| " + " | ".join(f"![{p}]({'' if p == first else p + '/'}fig5_spacetime_delay4.png)" for p in plants)
             + " |", "",
             "### Robustness maps (plant delay x plant alpha; stabilised: not diverged, final spatial std of rho "
             "< 0.5 veh/km; told: what each controller is told of the plant, `paper.maps`)", "",
             *_map_lines(robust, plants), "",
             "### Numerical checks", "", *_numerics_lines(table, plants, results, horizon_s), ""]
    text = "\n".join(lines)
    atomic_write_text(out_dir / "plants.md", text)
    write_json(out_dir / "plants.json", table)
    log("  plants: plants.md, plants.json, fig_plants_delay4.png; claims "
        + "; ".join(f"{p}: {table['claims'][p]}" for p in plants))
    return table, text
