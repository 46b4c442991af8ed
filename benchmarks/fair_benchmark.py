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
    python benchmarks/fair_benchmark.py --plant paper --tuned T.json --only backstepping_tuned \
        --merge-into full/paper.json                  # judge some laws again, into an earlier run's full JSON

``--strip`` drops a JSON's per-scenario measures (about 85 % of it) and its Markdown (the .md beside it), keeping
the tables, the checks, the scenarios (at float32's precision) and the provenance: the committed
docs/results/fair/split/ files (docs/results stays within its 6 MB); rerun the command to have the measures again
(``--resummarise`` needs them). Before it drops them it adds (as every run does) where each law diverges: its rate
in four equal bands of the plants' delay and of their ACC share over the distribution's ranges
(``diverged_by_plant`` in the JSON, a section of the Markdown).

``--only ROW...`` judges only those rows of the others' specs (and the reference row, backstepping, which every
table's ratios are taken to); ``--merge-into FULL`` puts their per-scenario
measures into an earlier run's JSON with its measures (not stripped) on the same plant, horizon and scenarios,
replacing the rows it had under the same names, and summarises it again (``merge``): a law re-tuned or retrained is
judged at its own cost, not at the whole table's (each law's measures depend only on it and the scenarios).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

import jaxtraffic as jt
from jaxtraffic.compare import ScenarioDistribution
from jaxtraffic.io.files import atomic_write_text, dumps_json, read_json, write_json
from jaxtraffic.paper import fair
from jaxtraffic.runs.policy import load_policy, policy_grid

PLANTS = {"paper": jt.TrafficParams(), "muscl": jt.TrafficParams(scheme="muscl"),
          "reference": jt.TrafficParams.reference()}


def main_job_runs(root: Path) -> list:
    """The main job's learned runs under ``root`` (``root/<law>``)."""
    loaded = {n: load_policy(root / n) for n in fair.laws.names(learned=True) if (root / n / "config.json").exists()}
    return fair.learned({n: c for n, (c, _) in loaded.items()}, {n: policy_grid(cfg) for n, (_, cfg) in loaded.items()})


BANDS = 4  # equal bands of each plant parameter's range
SECTION = "Where each law diverges"  # the Markdown section ``add_divergence_bands`` writes


def divergence_bands(d: dict[str, Any]) -> dict[str, Any]:
    """Each row's divergence rate (a fraction) in ``BANDS`` equal bands of the plants' delay (s) and ACC share over
    the distribution's ranges, from a run's JSON ``d`` (its per-scenario flags and its scenarios' draws)."""
    dist, scen = ScenarioDistribution(), d["scenarios"]
    out: dict[str, Any] = {"bands": {}, "n": {}, "rates": {k: {} for k in d["per_scenario"]}}
    for draw, (lo, hi) in (("delay", dist.delay_range), ("alpha", dist.alpha_range)):
        edges = np.linspace(lo, hi, BANDS + 1)
        band = np.clip(np.searchsorted(edges, np.asarray(scen[draw], float), side="right") - 1, 0, BANDS - 1)
        out["bands"][draw] = [[float(edges[b]), float(edges[b + 1])] for b in range(BANDS)]
        out["n"][draw] = [int((band == b).sum()) for b in range(BANDS)]
        for row, measures in d["per_scenario"].items():
            flags = np.asarray(measures["diverged"], bool)
            out["rates"][row][draw] = [float(flags[band == b].mean()) if (band == b).any() else None
                                       for b in range(BANDS)]
    return out


def add_divergence_bands(path: Path) -> None:
    """Add ``divergence_bands`` to the JSON at ``path`` (``diverged_by_plant``) and its Markdown (a section after the
    checks, replacing an earlier one)."""
    d = read_json(path)
    if not isinstance(d.get("per_scenario"), dict):
        raise ValueError(f"{path} holds no per-scenario measures; rerun the benchmark")
    by = d["diverged_by_plant"] = divergence_bands(d)
    units = {"delay": "s", "alpha": ""}
    head = [f"{'D' if k == 'delay' else 'alpha'} {lo:.3g}-{hi:.3g}{(' ' + units[k]) if units[k] else ''} (n {n})"
            for k in ("delay", "alpha") for (lo, hi), n in zip(by["bands"][k], by["n"][k], strict=True)]
    lines = [f"{SECTION} (diverged, % of the test scenarios in each band of the plant's delay D and ACC share "
             "alpha):", "", "| law | " + " | ".join(head) + " |", "|" + "---|" * (len(head) + 1)]
    for row, rates in by["rates"].items():
        cells = ["-" if r is None else f"{100 * r:.0f} %" for k in ("delay", "alpha") for r in rates[k]]
        lines.append(f"| {d['laws'].get(row, row)} | " + " | ".join(cells) + " |")
    md = list(d["markdown"])
    if any(line.startswith(SECTION) for line in md):
        md = md[:next(i for i, line in enumerate(md) if line.startswith(SECTION))]
        while md and not md[-1]:
            md.pop()
    d["markdown"] = [*md, "", *lines]
    write_json(path, d)
    atomic_write_text(path.with_suffix(".md"), "\n".join(d["markdown"]) + "\n")


def stripped(d: dict[str, Any]) -> dict[str, Any]:
    """A run's JSON as committed: without its per-scenario measures and its Markdown (the .md beside it), the
    scenarios' draws at float32's round-trip precision (9 significant digits: as the simulation read them)."""
    scen = {k: [float(f"{x:.9g}") if isinstance(x, float) else x for x in v] if isinstance(v, list) else v
            for k, v in d["scenarios"].items()}
    return {**{k: v for k, v in d.items() if k != "markdown"}, "scenarios": scen,
            "per_scenario": "omitted by fair_benchmark.py --strip: rerun the benchmark (provenance) to have them"}


def merge(full: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``full`` (a run's JSON with its per-scenario measures) with the rows of ``new`` (a run on the same plant,
    horizon and scenarios) put in: a row of the same name replaced in place, a new one appended; ``merged`` records
    each merge's rows and provenance. Raises ValueError when the runs do not share their scenarios."""
    if not isinstance(full.get("per_scenario"), dict):
        raise ValueError("the file to merge into holds no per-scenario measures; rerun the benchmark")
    for key in ("plant", "horizon_s", "scenarios"):
        if json.loads(dumps_json(full.get(key))) != json.loads(dumps_json(new.get(key))):
            raise ValueError(f"not the same {key}: the runs cannot be merged")
    out = {**full, "laws": {**full["laws"], **new["laws"]},
           "per_scenario": {**full["per_scenario"], **new["per_scenario"]}}
    out["merged"] = [*full.get("merged", []), {"rows": list(new["laws"]), "provenance": new["provenance"]}]
    return out


def only(specs: list, rows: list[str]) -> list:
    """The specs named in ``rows``, and the reference row (``fair.REFERENCE``), which every table's ratio column is
    taken to: a table without it cannot be written, so it is judged too (said on stdout when not asked for)."""
    if fair.REFERENCE not in rows:
        print(f"--only: adding the reference row {fair.REFERENCE} (the tables' ratios are to it)")
    return [sp for sp in specs if sp.name in {*rows, fair.REFERENCE}]


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
    ap.add_argument("--only", nargs="+", default=None, metavar="ROW", help="judge only these rows")
    ap.add_argument("--merge-into", type=Path, default=None, metavar="FULL",
                    help="put the rows judged into this earlier run's JSON (with its measures) and resummarise it")
    args = ap.parse_args()
    for path in args.strip:
        add_divergence_bands(path)
        write_json(path, stripped(read_json(path)))
        print(f"{path}: per-scenario measures dropped")
    if args.strip:
        return
    if args.resummarise:
        print("\n".join(fair.resummarise(args.resummarise)))
        return
    specs = (fair.model_based(read_json(args.tuned) if args.tuned else None)
             + (main_job_runs(args.runs) if args.runs else []) + (fair.split_runs(args.split_runs)
                                                                  if args.split_runs else []))
    if args.only:
        unknown = sorted(set(args.only) - {sp.name for sp in specs})
        if unknown:
            ap.error(f"--only: no such rows {unknown}; the rows: {', '.join(sp.name for sp in specs)}")
        specs = only(specs, args.only)
    t0 = time.perf_counter()
    noise = args.sensor_noise
    dist = ScenarioDistribution(sensor_noise_range=tuple(noise)) if noise else None
    name = f"{args.plant}_noise" if noise else args.plant
    out = fair.run(specs, args.plant, PLANTS[args.plant], None if args.merge_into else args.out, args.n,
                   args.horizon, args.seed, dist=dist, name=name)
    if args.merge_into:
        write_json(args.merge_into, merge(read_json(args.merge_into), out))
        print("\n".join(fair.resummarise(args.merge_into)))
        add_divergence_bands(args.merge_into)
        print(f"{args.merge_into}: rows {', '.join(out['laws'])} merged in, "
              f"{time.perf_counter() - t0:.0f} s")
        return
    if args.out is not None:
        add_divergence_bands(args.out / f"{name}.json")
        out = read_json(args.out / f"{name}.json")
    print(f"{args.plant} plant, {args.n} test scenarios (seed {args.seed}"
          + (f", sensor noise U({noise[0]:g}, {noise[1]:g})" if noise else "") + f"), {args.horizon:g} s, "
          f"{len(specs)} laws, {time.perf_counter() - t0:.0f} s")
    print("\n".join(out["markdown"]))


if __name__ == "__main__":
    main()
