"""Tune the model-based laws' design parameters on the train split (docs/model.md section 20): backstepping's and
the adaptive law's gain k and share of w's damping kept, with the learned laws' 25 m measurements, by the learned
residual's optimiser and budget (CEM, a population of 12 over 10 generations, on 36 scenarios of 300 s: as many as
the residual's training plants), on the paper's grid (``--plant paper``, the committed tuned.json) or on the
plant the CEM-trained learned laws train on (``--plant training``: their recipes' grid and scheme, MUSCL at 401
points, the laws acting on the paper's grid as theirs do). Writes the tuned parameters as JSON for
``benchmarks/fair_benchmark.py --tuned``.

    python benchmarks/tune_baselines.py --out docs/results/fair/tuned.json     # about 20 minutes on 2 cores
    python benchmarks/tune_baselines.py --plant training --out tuned-training.json
    python benchmarks/tune_baselines.py --sensor-noise 0 0.05 --out tuned-noise.json   # seeing noisy measurements

``--sensor-noise LO HI`` draws each train scenario's relative sensor error from U(LO, HI), as the comparison's
``--sensor-noise`` draws the test scenarios' (the same scenarios otherwise), and tunes the laws seeing it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jaxtraffic as jt
from jaxtraffic.compare import ScenarioDistribution, sample
from jaxtraffic.compare.tuning import tune
from jaxtraffic.io.files import write_json
from jaxtraffic.io.provenance import provenance
from jaxtraffic.paper.laws import TUNABLE
from jaxtraffic.paper.recipes import recipe

N_TRAIN = 36  # train scenarios: as many as the learned residual's training plants (train_split_sweep.py's CEM laws)
HORIZON_S = 300.0  # s
SEED = 0  # the split's seed (the same as the benchmark's)
CEM_RECIPE = "adaptive-residual"  # whose plant ``--plant training`` is (the robust schedule's is the same)
GRID_FIELDS = ("n_points", "scheme", "substeps")  # what ``--plant training`` takes from it


def plant(kind: str) -> jt.TrafficParams:
    """The nominal plant the baselines are tuned on: the paper's grid, or the CEM recipes' grid and scheme."""
    if kind == "paper":
        return jt.TrafficParams()
    trained_on = recipe(CEM_RECIPE).plant
    return jt.TrafficParams(**{k: getattr(trained_on, k) for k in GRID_FIELDS})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=N_TRAIN, help="train scenarios")
    ap.add_argument("--horizon", type=float, default=HORIZON_S, help="s")
    ap.add_argument("--seed", type=int, default=SEED, help="the split's seed (the same as the benchmark's)")
    ap.add_argument("--plant", choices=("paper", "training"), default="paper",
                    help="the paper's grid, or the plant the CEM-trained learned laws train on")
    ap.add_argument("--sensor-noise", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="tune seeing measurements with a relative error drawn from U(LO, HI) per scenario")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    base = plant(args.plant)
    dist = ScenarioDistribution(sensor_noise_range=tuple(args.sensor_noise)) if args.sensor_noise else \
        ScenarioDistribution()
    scen = sample(dist, "train", args.n, args.seed, base=base)
    out = {"scenarios": scen.describe(), "plant": {"kind": args.plant, **{k: getattr(base, k) for k in GRID_FIELDS}},
           "sensor_noise_range": list(dist.sensor_noise_range), "provenance": provenance(), "laws": {}}
    for name, t in TUNABLE.items():
        t0 = time.perf_counter()
        out["laws"][name] = {**tune(t, scen, base, horizon_s=args.horizon, seed=args.seed),
                             "wall_s": time.perf_counter() - t0}
        print(f"{name}: {out['laws'][name]['best']} in {out['laws'][name]['wall_s']:.0f} s", flush=True)
    write_json(args.out, out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
