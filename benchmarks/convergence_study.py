"""Convergence study of the closed loop under plant refinement: which discretisation is the reference plant.

Every controller acts on its own grid (the baselines on the paper's 5 m grid at 0.1 s, ``control.adapter``;
a learned run on its training grid), so only the plant is refined: a ladder of grids (201 .. 3201 points)
for both schemes, each with the fewest solver steps per 0.1 s that the CFL bound allows
(``TrafficParams.substeps``), plus the same grids with twice the solver steps (time refinement). For each
plant and controller: the density L2 at 300 s and 600 s and the speed L2 at 300 s, J_TTT, J_fuel and
J_comfort (with its a^2 and a_t^2 parts and without the switch-on step) over 300 s, and the time after which
the reward stays >= -0.1 (600 s horizon).

Convergence: a level is converged when every convergent metric is within ``--tol`` (5 %) of the next finer
level of the same scheme, a difference below the metric's absolute floor (``FLOORS``) counting as none. The
floors: 0.1 veh/km for the density L2 (float32 stagnation: near the equilibrium the solver's increments
fall below half an ulp of rho and the state stops moving at 0.01-0.1 veh/km, depending on the solver step;
float64 decays to 1e-6, BENCHMARKS.md), 0.005 m/s for the speed L2 and 5 s for the time to the reward target.
J_comfort is reported, not required: where the solution carries shocks it grows with 1/dx (the acceleration
of a vehicle crossing a shock is a delta).

    python benchmarks/convergence_study.py --out docs/results/convergence [--runs ppo=runs/default,...]

Writes convergence.json, convergence.md (the tables) and convergence.png (metric vs dx per scheme and
controller), and prints the coarsest converged level (of every loop, and of every loop without shocks).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

import jaxtraffic as jt
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.io.files import atomic_write_text, write_json  # noqa: E402
from jaxtraffic.io.provenance import provenance
from jaxtraffic.runs.policy import load_policy, policy_grid

LEVELS = ((201, 1), (401, 1), (801, 2), (1601, 4), (3201, 8))  # the fewest solver steps the CFL bound allows
METRICS = ("rho_L2_300", "rho_L2_600", "v_L2_300", "J_TTT", "J_fuel", "t_reward", "J_comfort", "J_comfort_a2",
           "J_comfort_at2", "J_comfort_no_switch_on")
CONVERGENT = ("rho_L2_300", "rho_L2_600", "v_L2_300", "J_TTT", "J_fuel", "t_reward")
FLOORS = {"rho_L2_300": 0.1, "rho_L2_600": 0.1, "v_L2_300": 0.005, "t_reward": 5.0}  # veh/km, m/s, s
SHOCK_LOOP = "lyapunov_D0"  # stabilises v first and lets the density wave steepen: its solution carries shocks
BASELINES = {"open_loop": (jt.open_loop, 0.0), "lyapunov_D0": (lambda: jt.lyapunov(1.0), 0.0),
             "backstepping": (lambda: jt.backstepping(4.0), 4.0)}


def run_one(ctrl, grid, plant: jt.TrafficParams) -> dict[str, float]:
    """The study's metrics of one controller on one plant (two rollouts: 300 s for the indices, 600 s)."""
    c = adapt(ctrl, grid or baseline_grid(plant), plant)
    short = jt.simulate(plant, c, n_steps=3000)
    long = jt.simulate(plant, c, n_steps=6000, record=jt.Record(every=100))
    m, ml = short.metrics, long.metrics
    return {"rho_L2_300": float(m["final_rho_L2"]), "rho_L2_600": float(ml["final_rho_L2"]),
            "v_L2_300": float(m["final_v_L2"]), "J_TTT": float(m["J_TTT"]), "J_fuel": float(m["J_fuel"]),
            "t_reward": float(ml["time_to_reward_target_s"]), "J_comfort": float(m["J_comfort"]),
            "J_comfort_a2": float(m["J_comfort_a2"]), "J_comfort_at2": float(m["J_comfort_at2"]),
            "J_comfort_no_switch_on": float(m["J_comfort_no_switch_on"]),
            "diverged_at_s": float(ml["diverged_at_s"])}


def rel_change(a: float, b: float, floor: float = 0.0) -> float:
    """|a - b| / |b|, 0 when both are within ``floor`` of each other (or both infinite)."""
    if math.isinf(a) and math.isinf(b):
        return 0.0
    if not (math.isfinite(a) and math.isfinite(b)):
        return math.inf
    if abs(a - b) <= floor:
        return 0.0
    return abs(a - b) / max(abs(b), 1e-30)


def converged_levels(data: dict, scheme: str, controllers: list[str], tol: float) -> dict[str, Any]:
    """Per space level of ``scheme``: the largest relative change of each convergent metric to the next finer
    level over the controllers, and whether all are within ``tol``."""
    out = {}
    for (n, s), (nf, sf) in zip(LEVELS[:-1], LEVELS[1:], strict=True):
        worst = {}
        for k in CONVERGENT:
            worst[k] = max(rel_change(data[f"{scheme}/{n}/{s}"][c][k], data[f"{scheme}/{nf}/{sf}"][c][k],
                                      FLOORS.get(k, 0.0)) for c in controllers)
        out[f"{n}/{s}"] = {"next": f"{nf}/{sf}", "worst": worst, "converged": all(v <= tol for v in worst.values())}
    return out


def coarsest_converged(conv: dict[str, Any]) -> str | None:
    """The coarsest level of one scheme from which every finer level is converged too."""
    levels = list(conv)
    for i, lvl in enumerate(levels):
        if all(conv[later]["converged"] for later in levels[i:]):
            return lvl
    return None


def table(data: dict, controllers: list[str], metric: str, schemes: tuple[str, ...]) -> list[str]:
    plants = [f"{sc}/{n}/{s}" for sc in schemes for n, s in sorted(set(LEVELS) | {(n, 2 * s) for n, s in LEVELS[:-1]})]
    plants = [p for p in plants if p in data]
    lines = ["| plant (scheme/points/solver steps) | " + " | ".join(controllers) + " |",
             "|---|" + "---|" * len(controllers)]
    for p in plants:
        lines.append(f"| {p} | " + " | ".join(f"{data[p][c][metric]:.4g}" for c in controllers) + " |")
    return lines


UNIT = {"rho_L2_300": "veh/km", "rho_L2_600": "veh/km", "J_TTT": "veh/km·m·s", "t_reward": "s",
        "J_comfort": "(m²/s⁴ + m²/s⁶)·veh/km·m·s", "J_comfort_a2": "m²/s⁴·veh/km·m·s"}  # the panels' units


def plot(path: Path, data: dict, controllers: list[str], schemes: tuple[str, ...]) -> None:
    """The metrics against the plant's dx, one panel each (``UNIT``), written as a palette PNG at ``path``."""
    from jaxtraffic.io.drawing import new_figure, save_figure

    metrics = tuple(UNIT)
    fig = new_figure(figsize=(13, 7))
    axes = fig.subplots(2, 3)
    dx = [1000.0 / (n - 1) for n, _ in LEVELS]
    for ax, k in zip(axes.ravel(), metrics, strict=True):
        for i, c in enumerate(controllers):
            for sc, ls in zip(schemes, ("--", "-"), strict=False):
                ys = [data.get(f"{sc}/{n}/{s}", {}).get(c, {}).get(k, np.nan) for n, s in LEVELS]
                ax.plot(dx, ys, ls, color=f"C{i}", marker="o", ms=3, label=f"{c} ({sc})")
        ax.set_xscale("log")
        ax.set_xticks(dx, [f"{d:g}" for d in dx])
        ax.minorticks_off()
        ax.set_yscale("log" if k != "J_TTT" else "linear")
        ax.invert_xaxis()
        ax.set_xlabel("plant dx (m)")
        ax.set_title(f"{k} ({UNIT[k]})", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=6, ncol=2)
    fig.suptitle("Closed loop under plant refinement (controllers on their own grids)")
    save_figure(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("results/convergence"))
    ap.add_argument("--runs", default="", help="learned runs to include, NAME=RUN_DIR,... (at their training delay)")
    ap.add_argument("--tol", type=float, default=0.05)
    ap.add_argument("--schemes", default="upwind,muscl")
    ap.add_argument("--from-json", type=Path, default=None,
                    help="redo the analysis and the outputs from an earlier convergence.json (no simulation)")
    args = ap.parse_args()
    schemes = tuple(args.schemes.split(","))
    if args.from_json is not None:
        earlier = json.loads(args.from_json.read_text())
        data = earlier["data"]  # (a metric never reached was written as null)
        data = {p: {c: {k: math.inf if v is None else v for k, v in m.items()} for c, m in by_ctrl.items()}
                for p, by_ctrl in data.items()}
        write_outputs(args.out, data, list(next(iter(data.values()))), schemes, args.tol, earlier["provenance"])
        return
    ctrls: dict[str, tuple[Any, Any, float]] = {k: (f(), None, d) for k, (f, d) in BASELINES.items()}
    for item in filter(None, args.runs.split(",")):
        name, run = item.split("=")
        ctrl, config = load_policy(run)
        ctrls[name] = (ctrl, policy_grid(config), float(config.plant.delay))
    plants = sorted({(sc, n, s) for sc in schemes for n, s in LEVELS}
                    | {(sc, n, 2 * s) for sc in schemes for n, s in LEVELS[:-1]}, key=lambda x: (x[0], x[1], x[2]))
    data: dict[str, dict[str, dict]] = {}
    t0 = time.perf_counter()
    for sc, n, s in plants:
        key = f"{sc}/{n}/{s}"
        data[key] = {}
        for name, (ctrl, grid, delay) in ctrls.items():
            data[key][name] = run_one(ctrl, grid, jt.TrafficParams(n_points=n, substeps=s, scheme=sc, delay=delay))
        print(f"{key:>16s}: " + " | ".join(f"{c} L2 {v['rho_L2_300']:.3f} J_c {v['J_comfort']:.4g}"
                                           for c, v in data[key].items()) + f"  ({time.perf_counter() - t0:.0f} s)",
              flush=True)
        jax.clear_caches()  # about 200 programs in one process: LLVM ran out of memory without this
    write_outputs(args.out, data, list(ctrls), schemes, args.tol)


def write_outputs(out: Path, data: dict, names: list[str], schemes: tuple[str, ...], tol: float,
                  simulated_by: dict | None = None) -> None:
    """The analysis of the study's data: convergence per scheme (all loops, and per loop), the reference.
    ``simulated_by``: the provenance of the simulations when they were run by another commit."""
    conv = {sc: converged_levels(data, sc, names, tol) for sc in schemes}
    per_loop = {sc: {c: coarsest_converged(converged_levels(data, sc, [c], tol)) for c in names} for sc in schemes}
    smooth = [c for c in names if c != SHOCK_LOOP]  # the loops whose solution has no shock
    conv_smooth = {sc: converged_levels(data, sc, smooth, tol) for sc in schemes}
    found = [(sc, coarsest_converged(conv[sc])) for sc in ("muscl", "upwind") if sc in conv]
    found_smooth = [(sc, coarsest_converged(conv_smooth[sc])) for sc in ("muscl", "upwind") if sc in conv]
    reference = next((f for f in found if f[1]), None)
    reference_smooth = next((f for f in found_smooth if f[1]), None)
    out.mkdir(parents=True, exist_ok=True)
    prov = provenance() if simulated_by is None else {**simulated_by, "analysis": provenance()}
    write_json(out / "convergence.json", {"provenance": prov, "tol": tol, "floors": FLOORS,
                                          "levels": LEVELS, "data": data, "convergence": conv,
                                          "coarsest_converged_per_loop": per_loop, "reference": reference,
                                          "reference_without_" + SHOCK_LOOP: reference_smooth})
    md = [f"# Convergence study (controllers on their own grids; tol {tol:.0%}, floors {FLOORS})", "",
          "## The coarsest level from which each closed loop is converged", "",
          "| scheme | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    md += [f"| {sc} | " + " | ".join(str(per_loop[sc][c]) for c in names) + " |" for sc in schemes]
    md.append("")
    for sc in schemes:
        md += [f"## {sc}: largest change of each convergent metric to the next finer level", "",
               "| level | next | " + " | ".join(CONVERGENT) + " | converged |",
               "|---|---|" + "---|" * (len(CONVERGENT) + 1)]
        for lvl, v in conv[sc].items():
            md.append(f"| {lvl} | {v['next']} | " + " | ".join(f"{100 * v['worst'][k]:.1f} %" for k in CONVERGENT)
                      + f" | {'yes' if v['converged'] else 'no'} |")
        md.append("")
    for metric in METRICS:
        md += [f"## {metric}", "", *table(data, names, metric, schemes), ""]
    md += [f"Coarsest level from which every loop is converged: {reference}; every loop but {SHOCK_LOOP} (whose "
           f"solution carries shocks): {reference_smooth}.", ""]
    atomic_write_text(out / "convergence.md", "\n".join(md))
    plot(out / "convergence.png", data, names, schemes)
    print(f"coarsest converged level (MUSCL first): every loop {reference}, every loop but {SHOCK_LOOP} "
          f"{reference_smooth}; outputs in {out}")


if __name__ == "__main__":
    main()
