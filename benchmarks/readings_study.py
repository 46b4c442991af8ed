"""Study, on the paper's grid (300 s): Table 2's baselines in both readings of the indices
under grid refinement and the MUSCL scheme, the comfort split and its dt dependence, and
backstepping under every reading of the alpha noise (8 seeds). Prints markdown tables.

    python benchmarks/readings_study.py [--part table|dt|noise|all] [--seeds 8]
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jaxtraffic.control import backstepping, open_loop
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper.scenarios import SCENARIOS, EvalConfig, run_batch
from jaxtraffic.paper.summaries import PAPER_TABLE2

KEYS = ("J_TTT", "J_fuel", "J_comfort", "J_fuel_kmh", "J_comfort_kmh", "J_comfort_a2", "J_comfort_at2",
        "J_comfort_switch_on", "J_comfort_no_switch_on")


def run(ctrl, cfg: EvalConfig, delay: float = 4.0, **plant) -> dict[str, float]:
    res = run_batch(ctrl, [cfg.nominal(delay=delay, **plant)], [0], cfg, record=False)
    return {k: float(np.asarray(res.metrics[k])[0]) for k in KEYS}


def table(horizon: float) -> None:
    ctrls = {"open_loop": open_loop(), "backstepping": backstepping(4.0, 1.0)}
    variants = {"upwind dx=5": EvalConfig(horizon_s=horizon), "upwind dx=2.5": EvalConfig(horizon_s=horizon, refine=2),
                "muscl dx=5": EvalConfig(horizon_s=horizon, scheme="muscl"),
                "muscl dx=2.5": EvalConfig(horizon_s=horizon, scheme="muscl", refine=2)}
    out = {}
    for v, cfg in variants.items():
        for c, ctrl in ctrls.items():
            t0 = time.perf_counter()
            out[(v, c)] = run(ctrl, cfg)
            print(f"<!-- {v} {c} {time.perf_counter() - t0:.1f} s -->", flush=True)
    print("| variant | controller | J_TTT | J_fuel SI | J_fuel km/h | J_comfort SI | J_comfort km/h | a^2 | a_t^2 "
          "| switch-on | without switch-on |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (v, c), m in out.items():
        print(f"| {v} | {c} | {m['J_TTT']:.4g} | {m['J_fuel']:.4g} | {m['J_fuel_kmh']:.4g} | {m['J_comfort']:.4g} "
              f"| {m['J_comfort_kmh']:.4g} | {m['J_comfort_a2']:.4g} | {m['J_comfort_at2']:.4g} "
              f"| {m['J_comfort_switch_on']:.4g} | {m['J_comfort_no_switch_on']:.4g} |")
    print("\n| paper | " + " | ".join(f"{c}: {PAPER_TABLE2['J_TTT'][c]:.1e} / {PAPER_TABLE2['J_fuel'][c]:.1e} / "
                                      f"{PAPER_TABLE2['J_comfort'][c]:.1e}" for c in ctrls) + " |")
    print("\nImprovements of backstepping over the open loop (%):\n")
    print("| variant | TTT | fuel SI | fuel km/h | comfort (either) | comfort without switch-on |")
    print("|---|---|---|---|---|---|")
    for v in variants:
        ol, bs = out[(v, "open_loop")], out[(v, "backstepping")]

        def imp(k, ol=ol, bs=bs):
            return 100 * (ol[k] - bs[k]) / ol[k]
        print(f"| {v} | {imp('J_TTT'):.2f} | {imp('J_fuel'):.2f} | {imp('J_fuel_kmh'):.2f} | {imp('J_comfort'):.1f} "
              f"| {imp('J_comfort_no_switch_on'):.1f} |")


def dt_study(horizon: float) -> None:
    print("| dt (s) | controller | J_comfort | a^2 part | a_t^2 part | switch-on step | without switch-on |")
    print("|---|---|---|---|---|---|---|")
    for dt in (0.1, 0.05, 0.025):
        cfg = EvalConfig(horizon_s=horizon, dt=dt)
        for c, ctrl in (("open_loop", open_loop()), ("backstepping", backstepping(4.0, 1.0))):
            m = run(ctrl, cfg)
            print(f"| {dt:g} | {c} | {m['J_comfort']:.4g} | {m['J_comfort_a2']:.4g} | {m['J_comfort_at2']:.4g} "
                  f"| {m['J_comfort_switch_on']:.4g} | {m['J_comfort_no_switch_on']:.4g} |", flush=True)


def noise(horizon: float, seeds: int) -> None:
    cfg = EvalConfig(horizon_s=horizon, seeds=tuple(range(seeds)))
    ctrl = backstepping(4.0, 1.0)
    print("| reading | backstepping stabilised | diverged | final rho L2 (veh/km), mean | per seed |")
    print("|---|---|---|---|---|")
    for sc in SCENARIOS:
        if not sc.seeded:
            continue
        envs = [cfg.nominal(delay=sc.plant_delay, alpha_noise=sc.alpha_noise)] * seeds
        res = run_batch(ctrl, envs, list(cfg.seeds), cfg, record=False, noise=sc.reading(cfg.dt, "backstepping"))
        m = jax.tree_util.tree_map(np.asarray, res.metrics)
        ok = (~m["diverged"]) & np.isfinite(m["time_to_reward_target_s"])
        l2 = m["final_rho_L2"]
        print(f"| {sc.name} | {int(ok.sum())}/{seeds} | {int(m['diverged'].sum())}/{seeds} | {l2.mean():.3g} "
              f"| {', '.join(f'{x:.3g}' for x in l2)} |", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", default="all", choices=("table", "dt", "noise", "all"))
    ap.add_argument("--horizon", type=float, default=300.0)
    ap.add_argument("--seeds", type=int, default=8)
    a = ap.parse_args()
    assert TrafficParams().n_points == 201
    if a.part in ("table", "all"):
        table(a.horizon)
    if a.part in ("dt", "all"):
        print()
        dt_study(a.horizon)
    if a.part in ("noise", "all"):
        print()
        noise(a.horizon, a.seeds)
