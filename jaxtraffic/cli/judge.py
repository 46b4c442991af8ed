"""``evaluate.py --judge --controller NAME=SOURCE:FUNCTION[:ARG]``: judge your own policy against the baselines
without the main job's training.

Every scenario of the paper (``paper.scenarios.SCENARIOS``) runs on each plant of ``--plants`` (the paper grid,
``--n-points`` or 201 points, upwind; the reference plant, ``--reference-grid``, MUSCL) with open loop, Lyapunov,
backstepping, adaptive backstepping (``control.adaptive_backstepping``: alpha estimated online, told D = 4 s like
backstepping) and the ``--controller`` policies; no PPO or gradient-trained controller is trained or loaded, no
robustness map, numerics check or claim is made. The outputs go to ``--out`` through the same staging as the main
job (``cli.staging``: an owned folder, replaced whole at the end): judge.json (every scenario's metrics per plant,
their units, the scenarios' legend and the comparison), REPORT.md and one figure per plant
(``judge_l2_delay4_PLANT.png``: the L2 norms over time at D = 4 s).

The comparison (``compare``): per scenario, each policy's final density L2 over backstepping's and over the
adaptive law's (a ratio below 1 is a win; within ``TIE`` of 1 a tie). A diverged run never wins: a policy that
diverged loses to a baseline that did not, a scenario where both diverged is no comparison, and REPORT.md shows
"diverged" instead of a diverged row's numbers (its indices are those of a frozen state). For the comparison with
the learned controllers run the main job with the same ``--controller`` (``python evaluate.py --controller ...``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jaxtraffic.io.files import atomic_write_text, to_jsonable
from jaxtraffic.io.provenance import provenance
from jaxtraffic.paper import laws
from jaxtraffic.paper.numerics import deploy
from jaxtraffic.paper.scenarios import SCENARIOS, EvalConfig, Outcome, initial_norms, run_scenarios
from jaxtraffic.paper.summaries import UNITS, summarise

ADAPTIVE = "adaptive_backstepping"
_ADAPTIVE_RUN = "adaptive backstepping"  # its name in run_scenarios: one a --controller cannot take (no spaces)
REFERENCES = {"backstepping": "backstepping", ADAPTIVE: "the adaptive law"}  # what each policy is compared with
TIE = 0.01  # a ratio within 1 +- TIE is a tie
UNIT_KEYS = ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward", "diverged")
# REPORT.md's columns: (metrics key, header with its unit: judge.json's)
COLUMNS = (("J_TTT", "J_TTT (veh/km·m·s)"), ("J_fuel", "J_fuel (ml/s·veh/km·m·s)"),
           ("J_comfort", "J_comfort ((m²/s⁴ + m²/s⁶)·veh/km·m·s)"), ("final_rho_L2", "final ρ L2 (veh/km)"),
           ("final_v_L2", "final v L2 (m/s)"), ("final_reward", "final reward (1)"))


def judge_plants(own: dict[str, Any], grids: dict[str, Any], configs: dict[str, EvalConfig], out_dir: Path,
                 meta: dict[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every scenario on each plant of ``configs`` for the baselines and ``own`` (name -> Controller, acting on
    ``grids[name]`` when given); writes judge.json, REPORT.md and the figures into ``out_dir``; returns
    judge.json's dict."""
    out_dir.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {
        "meta": {**meta, "controllers": sorted(own), "compared_with": list(REFERENCES), "provenance": provenance()},
        "units": {**{k: UNITS[k] for k in UNIT_KEYS},
                  "rho_L2_ratio_to_REF": "dimensionless: the policy's final_rho_L2 over REF's (comparison)"},
        "scenarios": legend(), "plants": {}}
    for plant, config in configs.items():
        t0 = time.perf_counter()
        log(f"== {plant} plant: {config.describe()}")
        ctrls = {**laws.build_model_based("all"), _ADAPTIVE_RUN: laws.build_model_based("map")[ADAPTIVE], **own}
        outcomes = run_scenarios(deploy(ctrls, grids, config), config, log)
        outcomes = {s: {ADAPTIVE if c == _ADAPTIVE_RUN else c: o for c, o in per.items()}
                    for s, per in outcomes.items()}
        init_l2 = initial_norms(config)
        scenarios = {s: {c: summarise(o, init_l2) for c, o in per.items()} for s, per in outcomes.items()}
        figure = f"judge_l2_delay4_{plant}.png"
        l2_figure(out_dir / figure, outcomes["delay4"], f"{plant} plant ({config.describe()})")
        result["plants"][plant] = {"config": config.describe(), "runtime_s": time.perf_counter() - t0,
                                   "scenarios": scenarios, "comparison": compare(scenarios, own),
                                   "figures": [figure]}
    result = to_jsonable(result)
    for res in result["plants"].values():
        res["summary"] = {c: summary_line(res["comparison"][c], c) for c in sorted(own)}
    atomic_write_text(out_dir / "judge.json", json.dumps(result, indent=1) + "\n")
    atomic_write_text(out_dir / "REPORT.md", report_text(result))
    return result


def legend() -> dict[str, str]:
    """Scenario name -> what its plant is and who runs in it (``paper.scenarios.SCENARIOS``)."""
    out = {}
    for sc in SCENARIOS:
        who = ("no backstepping (the plant has no delay); " if "backstepping" not in sc.controllers else "")
        seeds = "mean over the noise seeds; " if sc.seeded else ""
        out[sc.name] = f"{sc.description} ({who}{seeds}your policy runs in every scenario)"
    return out


def l2_figure(path: Path, delay4: dict[str, Outcome], where: str) -> None:
    """The L2 norms of the deviations over time at D = 4 s (``paper.plotting.plot_l2_norms``) at ``path``."""
    from jaxtraffic.paper.plotting import plot_l2_norms

    names = {ADAPTIVE: "adaptive backstepping"}
    series = {laws.short_label(c) if c in laws.LAWS else names.get(c, c): (o.rho_L2, o.v_L2) for c, o in delay4.items()}
    t = next(iter(delay4.values())).t
    plot_l2_norms(path, t, series, f"L2 norms of the deviations, plant delay D = 4 s: {where}")


def _verdict(mine: dict[str, Any], ref: dict[str, Any] | None) -> tuple[float | None, str]:
    """(final density L2 ratio mine / ref, "win" | "loss" | "tie" | "both diverged" | "n/a")."""
    if ref is None:
        return None, "n/a"
    if mine["diverged"] or ref["diverged"]:
        return None, ("both diverged" if mine["diverged"] and ref["diverged"] else
                      "loss" if mine["diverged"] else "win")
    a, b = mine["final_rho_L2"], ref["final_rho_L2"]
    if not b > 0:
        return None, "tie" if a == b else "loss"
    ratio = a / b
    return ratio, "tie" if abs(ratio - 1.0) <= TIE else ("win" if ratio < 1.0 else "loss")


def compare(scenarios: dict[str, dict[str, dict[str, Any]]], own: dict[str, Any]) -> dict[str, Any]:
    """Policy -> scenario -> {"diverged": whether the policy did, "rho_L2_ratio_to_REF": its final density L2 over
    REF's (None when either diverged or REF did not run), "vs_REF": its verdict} for each REF of ``REFERENCES``."""
    out: dict[str, Any] = {}
    for c in own:
        out[c] = {}
        for s, per in scenarios.items():
            if c not in per:
                continue
            row: dict[str, Any] = {"diverged": bool(per[c]["diverged"])}
            for ref in REFERENCES:
                row[f"rho_L2_ratio_to_{ref}"], row[f"vs_{ref}"] = _verdict(per[c], per.get(ref))
            out[c][s] = row
    return out


def summary_line(comparison: dict[str, dict[str, Any]], name: str) -> str:
    """One line: wins, losses and ties of ``name`` against each reference over the scenarios (a diverged run of
    the policy counts as a loss; scenarios where both diverged, or the reference did not run, are left out)."""
    parts = []
    for ref, label in REFERENCES.items():
        verdicts = [row[f"vs_{ref}"] for row in comparison.values()]
        n = sum(v in ("win", "loss", "tie") for v in verdicts)
        counts = {v: verdicts.count(v) for v in ("win", "loss", "tie")}
        parts.append(f"won {counts['win']}, lost {counts['loss']}, tied {counts['tie']} of {n} scenarios "
                     f"against {label}")
    diverged = [s for s, row in comparison.items() if row["diverged"]]
    return (f"{name}: " + "; ".join(parts) + " (final density L2, lower wins; ties within "
            f"{100 * TIE:g} %)" + (f"; diverged runs: {', '.join(diverged)}" if diverged else ""))


def _cell(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return "" if v is None else str(v)
    if isinstance(v, (int, float)):
        return f"{v:.4g}"
    return str(v)


def _ratio(v: float | None) -> str:
    return "–" if v is None else f"{v:#.3g}×"


def _diverged(m: dict[str, Any]) -> str:
    if not m["diverged"]:
        return "no"
    at = m.get("diverged_at_s")
    n = m.get("n_seeds", 1)
    seeds = f", {round(m['diverged_fraction'] * n)} of {n} seeds" if n > 1 and "diverged_fraction" in m else ""
    return "**yes**" + (f" (at t = {at:.4g} s{seeds})" if isinstance(at, (int, float)) else seeds)


def report_text(result: dict[str, Any]) -> str:
    """REPORT.md: per plant the win/loss summary, the comparison (ratios), the metrics with their units (a diverged
    row shows "diverged" instead of its numbers) and the figure; the scenarios' legend and the units."""
    mine = ", ".join(result["meta"]["controllers"])
    lines = ["# Your policy judged against the baselines", "",
             f"Controllers of yours: {mine}. Each is compared, scenario by scenario, with backstepping and with the "
             "adaptive law (adaptive backstepping, alpha estimated online) by its final density L2 (the ratio "
             f"yours / theirs: below 1 is a win, within {100 * TIE:g} % of 1 a tie). A diverged run never wins. No "
             "learned controller of jaxtraffic was trained or evaluated; for that comparison run the main job with "
             "the same --controller.", ""]
    order = [s.name for s in SCENARIOS]
    for plant, res in result["plants"].items():
        lines += [f"## {plant} plant ({res['config']})", "", "**Summary**:", ""]
        lines += [f"- {line}" for line in res.get("summary", {}).values()] + [""]
        lines += _comparison_table(res, order)
        lines += _metrics_table(res, order)
        lines += [f"![{f}]({f})" for f in res.get("figures", [])] + [""]
    lines += ["## Scenarios", "", "| scenario | plant and readings |", "|---|---|"]
    lines += [f"| {s} | {text} |" for s, text in result.get("scenarios", {}).items()] + [""]
    lines += ["## Units", ""] + [f"- {k}: {text}" for k, text in result.get("units", {}).items()]
    lines += ["- ratios are dimensionless", ""]
    return "\n".join(lines)


def _comparison_table(res: dict[str, Any], order: list[str]) -> list[str]:
    lines = ["| scenario | controller | final ρ L2 (veh/km) | ratio to backstepping (1) | vs backstepping "
             "| ratio to the adaptive law (1) | vs the adaptive law |", "|---|---|---|---|---|---|---|"]
    for c, per in res.get("comparison", {}).items():
        for s in sorted(per, key=order.index):
            row, m = per[s], res["scenarios"][s][c]
            l2 = "diverged" if m["diverged"] else f"{m['final_rho_L2']:.4g}"
            lines.append(f"| {s} | {c} | {l2} | {_ratio(row['rho_L2_ratio_to_backstepping'])} "
                         f"| {row['vs_backstepping']} | {_ratio(row[f'rho_L2_ratio_to_{ADAPTIVE}'])} "
                         f"| {row[f'vs_{ADAPTIVE}']} |")
    return lines + [""]


def _metrics_table(res: dict[str, Any], order: list[str]) -> list[str]:
    lines = ["| scenario | controller | " + " | ".join(h for _, h in COLUMNS) + " | diverged |",
             "|---|---|" + "---|" * (len(COLUMNS) + 1)]
    for s in sorted(res["scenarios"], key=order.index):
        for c, m in res["scenarios"][s].items():
            cells = (["diverged"] * len(COLUMNS) if m["diverged"] else
                     [_cell(m.get(k)) for k, _ in COLUMNS])
            lines.append(f"| {s} | {c} | " + " | ".join(cells) + f" | {_diverged(m)} |")
    return lines + [""]
