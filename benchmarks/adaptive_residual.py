"""The learned residual on top of adaptive backstepping (control.adaptive_residual; issue 38 item 3).

Evaluates gain tables of ``adaptive_residual`` (constant pairs, or the table of a trained run) against
backstepping and adaptive backstepping: the nominal point (reference plant, D = 4 s, alpha = 0.15, 300 s:
density L2 and J_comfort), the robustness map (``adaptive_map``'s cells, exclusions and criterion) and held-out
cells (the training plants of the recipe, offset from the map's cells).

    python benchmarks/adaptive_residual.py --nominal --pairs "0,0;0.1,0.4;-0.2,0.8"
    python benchmarks/adaptive_residual.py --map --plant reference --pairs "0,0;0.1,0.4"
    python benchmarks/adaptive_residual.py --map --plant reference --run runs/adaptive-residual
    python benchmarks/adaptive_residual.py --held-out --plant reference --run runs/adaptive-residual
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from adaptive_map import ALPHAS, DELAYS, STD_TOL, eval_config  # noqa: E402

from jaxtraffic.control import backstepping, open_loop, tell_delay  # noqa: E402
from jaxtraffic.control.adapter import adapt, baseline_grid  # noqa: E402
from jaxtraffic.control.adaptive_residual import ALPHA_KNOTS, DELAY_KNOTS, adaptive_residual  # noqa: E402
from jaxtraffic.paper.scenarios import EvalConfig, run_batch  # noqa: E402
from jaxtraffic.sim.metrics import VEH_PER_KM  # noqa: E402
from jaxtraffic.sim.units import INDEX_UNITS  # noqa: E402

HELD_OUT_DELAYS = (0.3, 1.7, 3.3, 4.7, 6.3, 7.7)  # s: the recipe's training delays (offset from the maps' cells)
HELD_OUT_ALPHAS = (0.125, 0.225, 0.325, 0.425, 0.525, 0.575)


def tables_from(pairs: str, run: str) -> tuple[list[str], np.ndarray]:
    """(labels, tables (P, Kd, Ka, 2)): constant pairs "eta2,eta3;..." and/or a trained run's table."""
    labels, tables = [], []
    for p in filter(None, pairs.split(";")):
        e2, e3 = (float(x) for x in p.split(","))
        labels.append(f"const({e2:g},{e3:g})")
        tables.append(np.broadcast_to([e2, e3], (len(DELAY_KNOTS), len(ALPHA_KNOTS), 2)))
    for r in filter(None, run.split(",")):
        summary = json.loads((Path(r) / "summary.json").read_text())
        labels.append(f"run {r}")
        tables.append(np.asarray(summary["residual"]["table"]))
    return labels, np.asarray(tables, np.float32)


def run_cells(cfg: EvalConfig, tables: np.ndarray, delays, alphas) -> dict[str, np.ndarray]:
    """Every table on every cell (delays[i], alphas[i]) in one batch: diverged, final std_x rho (veh/km), final
    rho L2 (veh/km), J_comfort, each (P, C)."""
    nom = cfg.nominal()
    n_p, n_c = len(tables), len(delays)
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(delays, alphas, strict=True)] * n_p
    c = adapt(adaptive_residual(), baseline_grid(nom), nom)
    c = tell_delay(c, jnp.asarray(np.tile(delays, n_p), jnp.float32))
    c = c.replace(settings=c.settings.replace(table=jnp.asarray(np.repeat(tables, n_c, axis=0))))
    res = run_batch(c, envs, [0] * len(envs), cfg, record=False, batch_controller=True, chunk_size=n_c)
    m = res.metrics
    return {"diverged": np.asarray(m["diverged"], bool).reshape(n_p, n_c),
            "std": VEH_PER_KM * np.std(np.asarray(res.final.rho), axis=-1).reshape(n_p, n_c),
            "rho_L2": np.asarray(m["final_rho_L2"]).reshape(n_p, n_c),
            "J_comfort": np.asarray(m["J_comfort"]).reshape(n_p, n_c)}


def excluded(cfg: EvalConfig, delays, alphas) -> np.ndarray:
    """The cells where the open loop diverges before the plant's delay has elapsed (``adaptive_map.summarise``)."""
    nom = cfg.nominal()
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(delays, alphas, strict=True)]
    res = run_batch(adapt(open_loop(), baseline_grid(nom), nom), envs, [0] * len(envs), cfg, record=False)
    step = np.asarray(res.final.diverged_step)
    return np.asarray(res.metrics["diverged"], bool) & (step >= 0) & (step < np.round(np.asarray(delays) / cfg.dt))


def baseline_cells(cfg: EvalConfig, delays, alphas) -> dict[str, np.ndarray]:
    """Backstepping told each cell's delay: diverged and final std, each (C,)."""
    nom = cfg.nominal()
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(delays, alphas, strict=True)]
    c = tell_delay(adapt(backstepping(), baseline_grid(nom), nom), jnp.asarray(delays, jnp.float32))
    res = run_batch(c, envs, [0] * len(envs), cfg, record=False, batch_controller=True, chunk_size=len(ALPHAS))
    return {"diverged": np.asarray(res.metrics["diverged"], bool),
            "std": VEH_PER_KM * np.std(np.asarray(res.final.rho), axis=-1)}


def count(div: np.ndarray, std: np.ndarray, keep: np.ndarray) -> tuple[int, int]:
    stab = ~div & (std < STD_TOL)
    return int((stab & keep).sum()), int((div & keep).sum())


def cells_report(cfg: EvalConfig, labels, tables, delays, alphas, what: str) -> dict:
    t0 = time.perf_counter()
    ex = excluded(cfg, delays, alphas)
    keep = ~ex
    out = {"cells": len(delays), "controllable": int(keep.sum()),
           "excluded": [(float(d), float(a)) for d, a, e in zip(delays, alphas, ex, strict=True) if e], "rows": {}}
    bs = baseline_cells(cfg, delays, alphas)
    out["rows"]["backstepping"] = count(bs["diverged"], bs["std"], keep)
    r = run_cells(cfg, tables, delays, alphas)
    for i, lab in enumerate(labels):
        out["rows"][lab] = count(r["diverged"][i], r["std"][i], keep)
        lost = keep & ~r["diverged"][0] & (r["std"][0] < STD_TOL) & ~(~r["diverged"][i] & (r["std"][i] < STD_TOL))
        out["rows"][lab] += ([(float(d), float(a)) for d, a in zip(np.asarray(delays)[lost], np.asarray(alphas)[lost],
                                                                   strict=True)],)
    print(f"{what} ({len(delays)} cells, {out['controllable']} controllable, excluded {out['excluded']}; "
          f"{time.perf_counter() - t0:.0f} s): stabilised / diverged")
    for lab, row in out["rows"].items():
        extra = f"  lost vs the first row: {row[2]}" if len(row) > 2 and row[2] else ""
        print(f"  {lab:<32s} {row[0]:3d} / {row[1]:3d}{extra}")
    return out


def nominal(labels, tables) -> dict:
    """Density L2 at 300 s and J_comfort at D = 4 s, alpha = 0.15 on the reference plant."""
    cfg = eval_config("reference", 300.0)
    nom = cfg.nominal()
    bs = run_batch(adapt(backstepping(4.0), baseline_grid(nom), nom), [nom.replace(delay=4.0)], [0], cfg, record=False)
    ref = (float(bs.metrics["final_rho_L2"][0]), float(bs.metrics["J_comfort"][0]))
    print(f"nominal point (reference plant, D 4 s, alpha 0.15, 300 s): backstepping rho L2 {ref[0]:.4f} veh/km, "
          f"J_comfort {ref[1]:.1f} {INDEX_UNITS['J_comfort']}")
    r = run_cells(cfg, tables, [4.0], [0.15])
    out = {"backstepping": ref}
    for i, lab in enumerate(labels):
        l2, jc = float(r["rho_L2"][i, 0]), float(r["J_comfort"][i, 0])
        out[lab] = (l2, jc)
        print(f"  {lab:<32s} rho L2 {l2:.4f} veh/km ({l2 / ref[0]:.3f}x)  J_comfort {jc:.1f} ({jc / ref[1]:.3f}x)"
              f"  diverged {bool(r['diverged'][i, 0])}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", choices=("paper", "reference", "refined"), default="reference")
    ap.add_argument("--pairs", default="0,0", help="constant tables 'eta2,eta3;...' (0,0: the adaptive law)")
    ap.add_argument("--run", default="", help="trained run directories, comma-separated (their summary's table)")
    ap.add_argument("--nominal", action="store_true")
    ap.add_argument("--map", action="store_true", help="the map's cells (adaptive_map.DELAYS x ALPHAS)")
    ap.add_argument("--held-out", action="store_true", help="the recipe's training cells (offset from the map)")
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    labels, tables = tables_from(args.pairs, args.run)
    out = {"labels": labels}
    if args.nominal:
        out["nominal"] = nominal(labels, tables)
    cfg = eval_config(args.plant)
    for flag, ds, als, what in ((args.map, DELAYS, ALPHAS, "map"),
                                (args.held_out, HELD_OUT_DELAYS, HELD_OUT_ALPHAS, "held-out cells")):
        if flag:
            dd, aa = (np.asarray(x).ravel() for x in zip(*itertools.product(ds, als), strict=True))
            out[what] = cells_report(cfg, labels, tables, dd, aa, f"{what} on the {args.plant} plant")
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
