"""The held-out comparison's chunking in the order of the scenarios' delays (``compare.protocol.delay_order``)
against chunks in the drawn order: the same law on the same test scenarios in one process, wall time of each and
whether every per-scenario measure is bit-identical.

    python benchmarks/bench_delay_order.py --n 256 --law backstepping
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import jaxtraffic as jt
from jaxtraffic.compare import LawSpec, ScenarioDistribution, evaluate_laws, sample
from jaxtraffic.control import adaptive_backstepping

LAWS = {"backstepping": lambda: jt.backstepping(4.0), "adaptive": lambda: adaptive_backstepping(4.0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=256, help="test scenarios")
    ap.add_argument("--chunk", type=int, default=64, help="scenarios per compiled call")
    ap.add_argument("--horizon", type=float, default=600.0, help="s")
    ap.add_argument("--law", choices=sorted(LAWS), default="backstepping")
    args = ap.parse_args()
    base = jt.TrafficParams()
    scen = sample(ScenarioDistribution(), "test", args.n, seed=0, base=base)
    law = [LawSpec(args.law, args.law, LAWS[args.law], told="delay")]
    evaluate_laws(law, sample(ScenarioDistribution(), "test", args.chunk, seed=1, base=base), base, args.horizon,
                  chunk=args.chunk, log=lambda s: None, release=False)  # compile once, outside the timings
    got, wall = {}, {}
    for by_delay in (False, True):
        t0 = time.perf_counter()
        got[by_delay] = evaluate_laws(law, scen, base, args.horizon, chunk=args.chunk, log=lambda s: None,
                                      release=False, by_delay=by_delay)[args.law]
        wall[by_delay] = time.perf_counter() - t0
    same = all(np.array_equal(got[True][k], got[False][k]) for k in got[False])
    print(f"{args.law}, {args.n} test scenarios (D uniform on 0-8 s), chunks of {args.chunk}, {args.horizon:g} s, "
          f"paper grid: drawn order {wall[False]:.1f} s, delay order {wall[True]:.1f} s "
          f"({wall[False] / wall[True]:.2f}x); per-scenario measures bit-identical: {same}")


if __name__ == "__main__":
    main()
