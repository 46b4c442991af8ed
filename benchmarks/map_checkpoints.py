#!/usr/bin/env python
"""Robustness-map cells of every member and checkpoint of a PPO run (issue 13, robust PPO).

For each member of the run and each of its checkpoints ("best": best.msgpack, "last": the state
training stopped in), the deterministic policy is rolled out on ``evaluate.py``'s robustness map
(``paper.scenarios.run_robustness``: plant delay x plant alpha, 600 s, nominal model alpha 0.15).
Printed per line: the cells it stabilises (not diverged and final std_x(rho) < 0.5 veh/km), the
cells where it diverges, and at the paper's scenario (D = 4 s, 300 s) its final density L2 and
J_comfort relative to backstepping's.

    python benchmarks/map_checkpoints.py RUN_DIR [--maps]
"""

from __future__ import annotations

import argparse
import itertools

import jaxtraffic as jt
from jaxtraffic.paper.scenarios import EvalConfig, run_robustness
from jaxtraffic.runs import load_policy
from jaxtraffic.sim.metrics import STABLE_STD

STD_MAX = STABLE_STD  # veh/km: the map's "stabilised" threshold


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a PPO run directory (train.py --out-dir)")
    ap.add_argument("--maps", action="store_true", help="also print each map ('#' stabilised)")
    args = ap.parse_args()
    p = jt.TrafficParams(delay=4.0)
    ref = jt.simulate(p, jt.backstepping(4.0), n_steps=3000).metrics
    for checkpoint in ("best", "last"):
        for member in itertools.count():
            try:
                ctrl, _ = load_policy(args.run, seed=member, checkpoint=checkpoint)
            except ValueError:  # no such member: all done
                break
            out = run_robustness({"ppo": ctrl}, EvalConfig(), log=lambda _: None)["ppo"]
            div = out["diverged"].astype(bool)
            stab = ~div & (out["final_rho_spatial_std"] < STD_MAX)
            m = jt.simulate(p, ctrl, n_steps=3000).metrics
            print(f"{checkpoint} member {member}: map {int(stab.sum())} stabilised / {int(div.sum())} diverged of "
                  f"{stab.size}; D = 4 s: rho L2 {float(m['final_rho_L2']):.3f} veh/km, J_comfort "
                  f"{float(m['J_comfort']) / float(ref['J_comfort']):.2f}x backstepping's", flush=True)
            if args.maps:
                print("\n".join("".join("#" if x else "." for x in row) for row in stab))


if __name__ == "__main__":
    main()
