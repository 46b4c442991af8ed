#!/usr/bin/env python
"""How far can the three-gain law reach on the robustness map? (issue 13, robust PPO)

The robustness map (``evaluate.py``, ``paper.scenarios.run_robustness``) counts the cells
(plant delay D x plant alpha, 600 s, no noise, nominal model alpha = 0.15) where a controller
stabilises the road: not diverged and final spatial standard deviation of rho < 0.5 veh/km.
Backstepping, given the true plant delay, stabilises 82 of the 204 cells.

A PPO gain policy outputs the three gains of ``control.gain_law``; on one cell the best such
policy can do is at least as well as the best *constant* gains for that cell. This script searches
a grid of constant gains (eta1, eta2, eta3) on every cell and reports, per cell, whether *any* of
them stabilises it: an oracle gain schedule (a different gain triple per cell, chosen with
knowledge of the outcome). Its count is the ceiling a policy that only schedules constant gains
by (D, alpha) could reach on this gain grid, and it is compared with backstepping's map. Also
reported: a schedule by the delay alone (backstepping is told the plant delay, not its alpha):
per delay, the one triple that stabilises most alphas; and the best single triple for the map.

    python benchmarks/gain_oracle.py                      # coarse grid (280 triples), JSON to stdout
    python benchmarks/gain_oracle.py --eta1=0.6,0.7,0.8,0.9,0.97 --eta2=-3,-2.5,-2,-1.5,-1 \
        --eta3=-3,-2.770561,-2.5,-2.25,-2                 # finer, around the coarse grid's best
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model  # noqa: E402  (benchmarks/machine.py)

from jaxtraffic import constant_gains, paper_initial_condition, simulate_batch, stack_params  # noqa: E402
from jaxtraffic.paper.scenarios import EvalConfig  # noqa: E402

STD_MAX = 0.5e-3  # veh/m: the map's "stabilised" threshold (0.5 veh/km)


def _picture(mask: np.ndarray) -> list[str]:
    """One string per delay row: '#' stabilised, '.' not."""
    return ["".join("#" if x else "." for x in row) for row in mask]


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eta1", type=_floats, default=_floats("-0.8,-0.4,0,0.4,0.8"))
    ap.add_argument("--eta2", type=_floats, default=_floats("-3,-2,-1,0,1,2,3"))
    ap.add_argument("--eta3", type=_floats, default=_floats("-3,-2.770561,-2,-1,0,1,2,3"))  # with Lyapunov's
    ap.add_argument("--horizon-s", type=float, default=600.0)
    ap.add_argument("--combos-per-call", type=int, default=20, help="gain triples per batched call")
    args = ap.parse_args()

    cfg = EvalConfig(horizon_s=args.horizon_s)
    nom = cfg.nominal()
    n_steps = cfg.n_steps
    dd, aa = np.meshgrid(np.asarray(cfg.robust_delays), np.asarray(cfg.robust_alphas), indexing="ij")
    cells = [(float(d), float(a)) for d, a in zip(dd.ravel(), aa.ravel(), strict=True)]
    combos = list(itertools.product(args.eta1, args.eta2, args.eta3))
    rho0, v0 = paper_initial_condition(nom)
    template = constant_gains()

    @jax.jit
    def run(params, gains):
        b = gains.shape[0]
        res = simulate_batch(params, template.replace(settings=gains), n_steps=n_steps, nominal=nom,
                             rho0=jnp.broadcast_to(rho0, (b, nom.n_points)),
                             v0=jnp.broadcast_to(v0, (b, nom.n_points)), batch_controller=True)
        return res.metrics["diverged"], jnp.std(res.final.rho, axis=-1)

    stab = np.zeros((len(combos), len(cells)), bool)
    t0 = time.perf_counter()
    for lo in range(0, len(combos), args.combos_per_call):
        part = combos[lo:lo + args.combos_per_call]
        envs = [nom.replace(delay=d, alpha=a) for _ in part for d, a in cells]
        gains = jnp.asarray([g for g in part for _ in cells], jnp.float32)
        div, std = jax.device_get(run(stack_params(*envs), gains))
        stab[lo:lo + len(part)] = ((~div) & (std < STD_MAX)).reshape(len(part), len(cells))
        print(f"  {lo + len(part)}/{len(combos)} gain triples, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    any_cell = stab.any(axis=0).reshape(dd.shape)
    per_combo = stab.sum(axis=1)
    best = int(np.argmax(per_combo))
    # a schedule by the delay alone (what backstepping is told): per delay row, the best triple
    rows = stab.reshape(len(combos), *dd.shape)
    per_delay = rows.sum(axis=2).max(axis=0)
    out = {
        "machine": cpu_model(), "horizon_s": args.horizon_s, "n_cells": len(cells), "n_gain_triples": len(combos),
        "grid": {"eta1": args.eta1, "eta2": args.eta2, "eta3": args.eta3},
        "oracle_schedule_cells": int(any_cell.sum()),
        "delay_schedule_cells": int(per_delay.sum()), "delay_schedule_per_delay": per_delay.tolist(),
        "best_single_triple": {"gains": combos[best], "cells": int(per_combo[best]),
                               "map": _picture(stab[best].reshape(dd.shape))},
        "top_triples": [{"gains": combos[i], "cells": int(per_combo[i])} for i in np.argsort(-per_combo)[:8]],
        "oracle_map": _picture(any_cell),
        "delays_s": list(map(float, cfg.robust_delays)), "alphas": list(map(float, cfg.robust_alphas)),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
