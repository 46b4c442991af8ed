"""The held-out comparison (docs/model.md section 20; ``jaxtraffic.paper.fair``): every registered law on the test
split of the scenario distribution, on one plant, over 600 s; prints the distributions (median [bootstrap 95 %
interval]), the held-out checks, and writes them as JSON and Markdown.

The rows: the registry's model-based laws as the paper has them, the predictor laws with the learned laws' 25 m
measurement filter, with --tuned those tuned on the train split (``tune_baselines.py``), with --runs the learned
laws as the main job trains them (on the paper's wave), with --split-runs those trained on the train split over
seeds (``train_split_sweep.py``): one row per seed and a line per law over its seeds.

    python benchmarks/fair_benchmark.py --plant paper --tuned docs/results/fair/tuned.json --runs docs/results/runs \\
        --split-runs runs-split --out docs/results/fair
    python benchmarks/fair_benchmark.py --plant muscl ...          # the other scheme on the paper grid
    python benchmarks/fair_benchmark.py --plant reference ...      # the converged plant (8x the cost per scenario)
    python benchmarks/fair_benchmark.py --plant paper --sensor-noise 0 0.05 ...   # each law seeing noisy measurements
    python benchmarks/fair_benchmark.py --strip docs/results/fair/split/paper.json   # keep the summaries only

``--strip`` drops a JSON's per-scenario measures (about 85 % of it), keeping the tables, the checks, the scenarios
and the provenance: the committed docs/results/fair/split/ files (docs/results stays within its 6 MB); rerun the
command to have the measures again (``--resummarise`` needs them).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jaxtraffic as jt
from jaxtraffic.compare import ScenarioDistribution
from jaxtraffic.io.files import read_json, write_json
from jaxtraffic.paper import fair
from jaxtraffic.runs.policy import load_policy, policy_grid

PLANTS = {"paper": jt.TrafficParams(), "muscl": jt.TrafficParams(scheme="muscl"),
          "reference": jt.TrafficParams.reference()}


def main_job_runs(root: Path) -> list:
    """The main job's learned runs under ``root`` (``root/<law>``)."""
    loaded = {n: load_policy(root / n) for n in fair.laws.names(learned=True) if (root / n / "config.json").exists()}
    return fair.learned({n: c for n, (c, _) in loaded.items()}, {n: policy_grid(cfg) for n, (_, cfg) in loaded.items()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", choices=sorted(PLANTS), default="paper")
    ap.add_argument("--n", type=int, default=fair.N_TEST, help="test scenarios")
    ap.add_argument("--seed", type=int, default=0, help="the split's seed")
    ap.add_argument("--horizon", type=float, default=fair.HORIZON_S, help="s")
    ap.add_argument("--runs", type=Path, default=None, help="the main job's learned runs (e.g. docs/results/runs)")
    ap.add_argument("--tuned", type=Path, default=None, help="tuned parameters (benchmarks/tune_baselines.py)")
    ap.add_argument("--split-runs", type=Path, default=None, help="split-trained runs (train_split_sweep.py)")
    ap.add_argument("--sensor-noise", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="draw each scenario's relative sensor error from U(LO, HI) (jaxtraffic.control.noise); "
                         "the files are then <plant>_noise.json / .md")
    ap.add_argument("--out", type=Path, default=None, help="folder of <plant>.json and <plant>.md")
    ap.add_argument("--resummarise", type=Path, default=None, help="only rewrite this JSON's tables and checks")
    ap.add_argument("--strip", type=Path, nargs="*", default=(), help="only drop these JSONs' per-scenario measures")
    args = ap.parse_args()
    for path in args.strip:
        d = read_json(path)
        d["per_scenario"] = "omitted by fair_benchmark.py --strip: rerun the benchmark (provenance) to have them"
        write_json(path, d)
        print(f"{path}: per-scenario measures dropped")
    if args.strip:
        return
    if args.resummarise:
        print("\n".join(fair.resummarise(args.resummarise)))
        return
    specs = (fair.model_based(read_json(args.tuned) if args.tuned else None)
             + (main_job_runs(args.runs) if args.runs else []) + (fair.split_runs(args.split_runs)
                                                                  if args.split_runs else []))
    t0 = time.perf_counter()
    noise = args.sensor_noise
    dist = ScenarioDistribution(sensor_noise_range=tuple(noise)) if noise else None
    out = fair.run(specs, args.plant, PLANTS[args.plant], args.out, args.n, args.horizon, args.seed, dist=dist,
                   name=f"{args.plant}_noise" if noise else None)
    print(f"{args.plant} plant, {args.n} test scenarios (seed {args.seed}"
          + (f", sensor noise U({noise[0]:g}, {noise[1]:g})" if noise else "") + f"), {args.horizon:g} s, "
          f"{len(specs)} laws, {time.perf_counter() - t0:.0f} s")
    print("\n".join(out["markdown"]))


if __name__ == "__main__":
    main()
