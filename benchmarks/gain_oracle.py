#!/usr/bin/env python
"""How far can the three-gain law reach on the robustness map? The oracle rows (``jaxtraffic.paper.oracle``).

Rolls out a grid of constant gain triples (eta1, eta2, eta3) of the filtered three-gain law on every cell of
the robustness map (plant delay x plant alpha, 600 s, no noise; *stabilised*: not diverged and final
std_x(rho) < 0.5 veh/km) and reports three oracles chosen with knowledge of the outcome: the best single
triple, the best triple per delay (a law told the delay, not alpha, as backstepping is) and the best per
cell. ``--out DIR`` writes ``DIR/PLANT.json``, which ``evaluate.py --oracle-dir DIR`` draws beside the
controllers' maps and tabulates in REPORT.md.

    python benchmarks/gain_oracle.py --plant reference --out docs/results/oracle   # 9 x 6 map, 90 triples
    python benchmarks/gain_oracle.py --plant paper --out docs/results/oracle       # 17 x 12 map
    python benchmarks/gain_oracle.py --eta1=0 --eta2=-1 --eta3=-1.5,-2             # a few triples, JSON to stdout
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model, load  # noqa: E402  (benchmarks/machine.py)

from jaxtraffic.control.gain_law import FILTER_SIGMA  # noqa: E402
from jaxtraffic.io.files import write_json  # noqa: E402
from jaxtraffic.io.provenance import provenance  # noqa: E402
from jaxtraffic.paper.oracle import (  # noqa: E402
    DEFAULT_GRID,
    gain_grid_map,
    grid_triples,
    oracle_json,
    oracle_rows,
)
from jaxtraffic.paper.scenarios import EvalConfig, robust_axis  # noqa: E402
from jaxtraffic.sim.metrics import STABLE_STD  # noqa: E402

MAPS = {"paper": (17, 12), "reference": (9, 6)}  # evaluate.py's default map sizes per plant


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", choices=tuple(MAPS), default="reference")
    for name, values in DEFAULT_GRID.items():
        ap.add_argument(f"--{name}", type=_floats, default=list(values))
    ap.add_argument("--filter-sigma", type=float, default=FILTER_SIGMA, help="the law's filter width, m")
    ap.add_argument("--horizon-s", type=float, default=600.0)
    ap.add_argument("--out", type=Path, default=None, help="write PLANT.json here (default: JSON to stdout)")
    args = ap.parse_args()

    nd, na = MAPS[args.plant]
    axes = {"robust_delays": robust_axis(nd, 0.0, 8.0, 0.1), "robust_alphas": robust_axis(na, 0.05, 0.6),
            "robust_horizon_s": args.horizon_s, "numerics_check": False}
    cfg = EvalConfig.reference(**axes) if args.plant == "reference" else EvalConfig(**axes)
    triples = grid_triples(args.eta1, args.eta2, args.eta3)
    t0 = time.perf_counter()
    div, std = gain_grid_map(cfg, triples, args.filter_sigma, log=lambda m: print(m, file=sys.stderr, flush=True))
    rows = oracle_rows(triples, div, std)
    stab = ~div & (std < STABLE_STD)
    per_triple = stab.reshape(len(triples), -1).sum(axis=1)
    out = oracle_json(cfg, triples, rows, args.filter_sigma, extra={
        "grid": {"eta1": args.eta1, "eta2": args.eta2, "eta3": args.eta3},
        "top_triples": [{"gains": triples[i], "stabilised": int(per_triple[i]),
                         "diverged": int(div[i].sum())} for i in np.argsort(-per_triple, kind="stable")[:8]],
        "wall_s": round(time.perf_counter() - t0, 1), "machine": cpu_model(), "load": load(),
        "provenance": provenance()})
    summary = {k: (r["stabilised_cells"], r["diverged_cells"]) for k, r in out["rows"].items()}
    print(f"{args.plant}: {len(triples)} triples x {div[0].size} cells in {out['wall_s']} s; "
          f"(stabilised, diverged): {summary}", file=sys.stderr)
    if args.out is None:
        print(json.dumps(out, indent=1))
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        write_json(args.out / f"{args.plant}.json", out)
        print(f"wrote {args.out / (args.plant + '.json')}", file=sys.stderr)


if __name__ == "__main__":
    main()
