#!/usr/bin/env python
"""Rerun the main job and say whether each headline claim of the results page (docs/main-job.md) still holds
(on the paper's grid, on the reference plant, and the learned controllers' certificates).

    python benchmarks/reproduce.py [--out DIR] [--skip-run] [--reference docs/results]

Runs ``python evaluate.py --out DIR`` from an empty working directory (so every policy is trained
anew into its runs/, as on a fresh clone; ``--skip-run`` only re-checks an existing DIR), then checks the headline
claims below on DIR/metrics.json and prints, for each, PASS or FAIL with the numbers, and the
relative change of the key numbers against the committed ``--reference`` outputs. Exit status 0
when every claim holds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _d4(m: dict, c: str) -> dict:
    return m["delay4"].get(c, {})


def _beats_backstepping(c: str, j_ratio: float = 1.0) -> Callable[[dict], tuple[bool, str]]:
    """Final rho L2 below backstepping's and J_comfort below ``j_ratio`` x backstepping's (D = 4 s)."""
    def check(m: dict) -> tuple[bool, str]:
        x, b = _d4(m, c), _d4(m, "backstepping")
        if not x:
            return False, f"{c} not evaluated"
        ok = ((not x["diverged"]) and x["final_rho_L2"] < b["final_rho_L2"]
              and x["J_comfort"] < j_ratio * b["J_comfort"])
        return ok, (f"rho L2 {x['final_rho_L2']:.3f} vs {b['final_rho_L2']:.3f} veh/km, "
                    f"J_comfort {x['J_comfort']:.4g} vs {b['J_comfort']:.4g} (m²/s⁴ + m²/s⁶)·veh/km·m·s")
    return check


def _stabilises(scenario: str, c: str) -> Callable[[dict], tuple[bool, str]]:
    def check(m: dict) -> tuple[bool, str]:
        e = m[scenario].get(c)
        if e is None:
            return False, f"{c} not evaluated in {scenario}"
        t = e.get("time_to_reward_-0.1_s")
        return (not e["diverged"]) and t is not None, f"reward >= -0.1 from {t} s, diverged {e['diverged']}"
    return check


def _lyapunov_fails_with_delay(m: dict) -> tuple[bool, str]:
    e = m["delay4"]["lyapunov"]
    return e.get("time_to_reward_-0.1_s") is None, f"final rho L2 {e['final_rho_L2']:.3g} veh/km"


CLAIMS: dict[str, Callable[[dict], tuple[bool, str]]] = {
    "Lyapunov stabilises without delay": _stabilises("delay0", "lyapunov"),
    "Lyapunov does not stabilise with D = 4 s": _lyapunov_fails_with_delay,
    "backstepping stabilises with D = 4 s": _stabilises("delay4", "backstepping"),
    "PPO stabilises with D = 4 s": _stabilises("delay4", "ppo"),
    # the seed sweep's criterion (benchmarks/bench_ppo_seeds.py): L2 below, J_comfort at most 1.2x
    "PPO at D = 4 s: rho L2 below backstepping's, J_comfort <= 1.2x": _beats_backstepping("ppo", 1.2),
    "gradient gains beat backstepping at D = 4 s": _beats_backstepping("grad_gains"),
    "gradient network beats backstepping at D = 4 s": _beats_backstepping("grad_network"),
}
# on the reference plant (DIR/reference/metrics.json): the learned controllers against backstepping, and
# each within 10 % of itself on the plant refined twice (the evaluation's numerical check)
def _converged(c: str, tol: float = 0.10) -> Callable[[dict], tuple[bool, str]]:
    def check(m: dict) -> tuple[bool, str]:
        rel = m.get("numerics", {}).get("rel_diff", {}).get("refined", {}).get(c)
        if not rel:
            return False, f"{c}: no numerical check"
        worst = max(abs(rel["final_rho_L2"]), abs(rel["J_comfort"]))
        return worst < tol, f"largest change on the refined plant {100 * worst:.1f} %"
    return check


REFERENCE_CLAIMS: dict[str, Callable[[dict], tuple[bool, str]]] = {
    "reference plant: PPO rho L2 below backstepping's, J_comfort <= 1.2x": _beats_backstepping("ppo", 1.2),
    "reference plant: gradient gains beat backstepping": _beats_backstepping("grad_gains"),
    "reference plant: gradient network beats backstepping": _beats_backstepping("grad_network"),
    **{f"reference plant: {c} within 10 % on the refined plant": _converged(c)
       for c in ("backstepping", "ppo", "grad_gains", "grad_network")},
}
KEY_NUMBERS = [("delay4", c, k) for c in ("backstepping", "ppo", "grad_gains", "grad_network")
               for k in ("final_rho_L2", "J_comfort")]


BASELINES = ("open_loop", "lyapunov", "backstepping")
README_MARK = ("<!-- headline: learned vs backstepping (benchmarks/reproduce.py) -->", "<!-- /headline -->")
FAIR_MARK = ("<!-- headline: fair comparison (benchmarks/reproduce.py) -->", "<!-- /headline -->")
MAP_MARK = ("<!-- headline: robustness maps (benchmarks/reproduce.py) -->", "<!-- /headline -->")
VERDICT_MARK = ("<!-- headline: fair comparison elsewhere (benchmarks/reproduce.py) -->", "<!-- /headline -->")
PPO_MARK = ("<!-- headline: where PPO diverges (benchmarks/reproduce.py) -->", "<!-- /headline -->")
NOISE_MARK = ("<!-- headline: trained under noise (benchmarks/reproduce.py) -->", "<!-- /headline -->")
# the held-out tables that test the paper grid's verdict: the other scheme, the converged plant, sensor noise
ELSEWHERE = {"muscl": "with MUSCL", "reference": "on the reference plant",
             "paper_noise": "on the paper grid under sensor noise", "muscl_noise": "with MUSCL under sensor noise",
             "reference_noise": "on the reference plant under sensor noise"}


def headline(out: Path) -> str:
    """The README's headline ratio, from DIR/plants.json: the learned laws' density L2 at 300 s over
    backstepping's at D = 4 s on the reference plant, as a range."""
    ref = json.loads((out / "plants.json").read_text())["delay4"]["reference"]
    ratios = [v["final_rho_L2"] / ref["backstepping"]["final_rho_L2"] for k, v in ref.items() if k not in BASELINES]
    return f"density L2 {min(ratios):.2f}-{max(ratios):.2f}x backstepping's at 300 s"


def fair_headline(out: Path) -> str:
    """The README's headline of the held-out comparison, from DIR/fair/split/paper.json (benchmarks/fair_benchmark.py
    with the learned laws trained on the train split over seeds)."""
    d = json.loads((out / "fair" / "split" / "paper.json").read_text())
    c, labels, n = d["checks"], d["laws"], d["scenarios"]["n"]
    lo, hi = c["ratio_ci95"]
    seeds = c.get("seeds") or {}
    n_seeds = sorted({len(v["seeds"]) for v in seeds.values()})
    base = [v for k, v in c.items() if k.endswith("_vs_adaptive_backstepping")]
    return (f"on {n} held-out scenarios (paper grid, {d['horizon_s']:g} s), with every learned law trained on the "
            f"train split ({'-'.join(map(str, n_seeds)) or 'no'} seeds), the best learned law, "
            f"{labels[c['best_learned']]} (its median seed), has {c['ratio']:.2f}x [{lo:.2f}, {hi:.2f}] the "
            f"median time-averaged density L2 of the best model-based law, {labels[c['best_model_based']]} (the ratio "
            f"of the medians, paired-bootstrap 95 % interval): the frontier of 0.8x is "
            f"{'reached' if c['frontier'] else 'not reached'}; the learned residual's held-out check against its "
            f"base, the adaptive law, holds for {sum(base)} of {len(base)} seeds")


def frontiers(folder: Path, tables: dict[str, str]) -> list[str]:
    """Per table ``folder/<name>.json`` present (``tables``: name -> where), the best learned law against the best
    model-based law: the frontier's ratio and interval, as ``fair_headline``."""
    parts = []
    for name, where in tables.items():
        path = folder / f"{name}.json"
        if not path.exists():
            continue
        d = json.loads(path.read_text())
        c, n = d["checks"], d["scenarios"]["n"]
        lo, hi = c["ratio_ci95"]
        noise = d["scenarios"].get("sensor_noise") or [0.0]
        level = f", relative error U({min(noise):.2f}, {max(noise):.2f})" if max(noise) > 0 else ""
        parts.append(f"{where} ({n} scenarios{level}) {c['ratio']:.2f}x [{lo:.2f}, {hi:.2f}], frontier "
                     f"{'reached' if c['frontier'] else 'not reached'}")
    return parts


def elsewhere_headline(out: Path) -> str:
    """The README's line on the verdict's robustness, from DIR/fair/split/{muscl,reference}{,_noise}.json and
    paper_noise.json (those present)."""
    return ("the best learned law against the best model-based law elsewhere (the ratio of the medians): "
            + "; ".join(frontiers(out / "fair" / "split", ELSEWHERE)))


def noise_headline(out: Path) -> str:
    """The README's line on the learned laws trained under sensor noise, from
    DIR/fair/trained_under_noise/{paper,muscl,reference}_noise.json (those present): their best against the best
    model-based law of the same rows (the baselines tuned under the noise among them), and how often PPO trained
    so diverges (paper grid, per seed)."""
    folder = out / "fair" / "trained_under_noise"
    where = {k: v.split(" under")[0] for k, v in ELSEWHERE.items() if k.endswith("_noise")}
    line = ("with the learned laws trained and the baselines tuned under the sensor noise they are judged with, "
            "the best learned law against the best model-based law (the ratio of the medians): "
            + "; ".join(frontiers(folder, where)))
    d = json.loads((folder / "paper_noise.json").read_text())
    rows = sorted(k for k in d["laws"] if k.startswith("ppo_split_s"))
    if rows:
        n = d["scenarios"]["n"]
        failed = [round(d["summary"][k]["diverged_rate"]["value"] * n) for k in rows]
        line += (f"; PPO trained so diverges on {', '.join(map(str, failed))} of {n} (paper grid, seeds "
                 f"{', '.join(k.rsplit('_s', 1)[1] for k in rows)})")
    return line


def ppo_headline(out: Path) -> str:
    """The README's line on where the split-trained PPO runs diverge, from DIR/fair/split/paper.json (its failure
    count per seed and ``diverged_by_plant``, ``fair_benchmark.py``): in the lowest band of ACC share and above it."""
    d = json.loads((out / "fair" / "split" / "paper.json").read_text())
    rows = sorted(k for k in d["laws"] if k.startswith("ppo_split_s"))
    n, by = d["scenarios"]["n"], d["diverged_by_plant"]
    failed = [round(d["summary"][k]["diverged_rate"]["value"] * n) for k in rows]
    low = [by["rates"][k]["alpha"][0] for k in rows]
    high = [r for k in rows for r in by["rates"][k]["alpha"][1:] if r is not None]
    delay = [r for k in rows for r in by["rates"][k]["delay"] if r is not None]
    (a_lo, a_mid), a_hi = by["bands"]["alpha"][0], by["bands"]["alpha"][-1][1]
    d_lo, d_hi = by["bands"]["delay"][0][0], by["bands"]["delay"][-1][1]
    return (f"diverges on {', '.join(map(str, failed))} of {n} test scenarios (paper grid, seeds "
            f"{', '.join(k.rsplit('_s', 1)[1] for k in rows)}): on {100 * min(low):.0f}-{100 * max(low):.0f} % of "
            f"the plants with an ACC share of {a_lo:.2g}-{a_mid:.2g}, on {100 * min(high):.0f}-{100 * max(high):.0f} % "
            f"in each band above it up to {a_hi:.2g}, and on {100 * min(delay):.0f}-{100 * max(delay):.0f} % in each "
            f"band of delay from {d_lo:g} to {d_hi:g} s")


def map_headline(out: Path) -> str:
    """The README's robustness-map counts, from DIR/robustness.json and DIR/reference/robustness.json: the cells
    that stay stabilised (and those that diverge) of the controllable ones, for backstepping, the adaptive law and
    the best learned law."""
    parts = []
    for plant, path in (("the paper grid", out / "robustness.json"), ("the reference plant",
                                                                     out / "reference" / "robustness.json")):
        t = json.loads(path.read_text())["table"]
        rows, n, key = t["rows"], t["controllable"], "stays_stabilised"
        learned = [k for k in rows if k.startswith(("ppo", "grad_"))]
        best = max(learned, key=lambda k: (rows[k][key], -rows[k]["diverged"]))
        text = ", ".join(f"{name} {rows[k][key]} ({rows[k]['diverged']} diverged)" for name, k in
                         (("backstepping", "backstepping"), ("adaptive backstepping", "adaptive_backstepping"),
                          (f"the best learned law ({best})", best)))
        parts.append(f"on {plant}, of {n} controllable cells: {text}")
    return "cells that stay stabilised over the last 150 s of 600 s " + "; ".join(parts)


def readme_claim(out: Path, write: bool, mark: tuple[str, str] = README_MARK,
                 make: Callable[[Path], str] = headline) -> tuple[bool, str]:
    """Whether the README's headline between ``mark`` is the one ``make`` gives from DIR (``write``: make it so)."""
    readme = ROOT / "README.md"
    text, want = readme.read_text(), make(out)
    a = text.find(mark[0])
    b = text.find(mark[1], a + 1)
    if a < 0 or b < a:
        return False, f"no {mark[0]} ... {mark[1]} in README.md"
    got = text[a + len(mark[0]):b]
    if write and got != want:
        readme.write_text(text[:a + len(mark[0])] + want + text[b:])
        got = want
    return got == want, f"README says {got!r}; the results give {want!r}"


def certificates(out: Path) -> dict[str, tuple[bool, str]]:
    """Each exported learned controller (DIR/runs/NAME/summary.json) is certified at its nominal (D, alpha),
    where the certificate applies (a law it does not model, ``"applies": false``, e.g. the residual on adaptive
    backstepping, is not a claim of certification)."""
    res = {}
    for run in sorted((out / "runs").glob("*/summary.json")):
        cert = json.loads(run.read_text()).get("certificate") or {}
        if cert.get("applies", True) is False:
            continue
        growth = cert.get("max_growth")
        word = "?" if growth is None else ("certified" if growth <= 0 else "marginal" if cert.get("stable")
                                           else "not certified")
        res[f"{run.parent.name} passes the certificate check"] = (
            bool(cert.get("stable")), f"{word}: max growth {growth} /s at {cert.get('delay')} s")
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="output directory (default: a temporary one)")
    ap.add_argument("--skip-run", action="store_true", help="only check an existing --out")
    ap.add_argument("--reference", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--write-readme", action="store_true", help="write the README's headline from --out's results")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="jaxtraffic-reproduce-"))
    if not args.skip_run:
        work = Path(tempfile.mkdtemp(prefix="jaxtraffic-runs-"))  # its runs/ holds the freshly trained policies
        subprocess.run([sys.executable, str(ROOT / "evaluate.py"), "--out", str(out.resolve())], check=True, cwd=work)
    m = json.loads((out / "metrics.json").read_text())
    results = {name: check(m) for name, check in CLAIMS.items()}
    if (out / "reference" / "metrics.json").exists():
        mr = json.loads((out / "reference" / "metrics.json").read_text())
        results.update({name: check(mr) for name, check in REFERENCE_CLAIMS.items()})
    results.update(certificates(out))
    if (out / "plants.json").exists():
        results["the README's headline is the results'"] = readme_claim(out, args.write_readme)
    if (out / "fair" / "split" / "paper.json").exists():
        results["the README's fair-comparison headline is the results'"] = readme_claim(
            out, args.write_readme, FAIR_MARK, fair_headline)
    if any((out / "fair" / "split" / f"{n}.json").exists() for n in ELSEWHERE):
        results["the README's fair-comparison robustness line is the results'"] = readme_claim(
            out, args.write_readme, VERDICT_MARK, elsewhere_headline)
    if (out / "fair" / "split" / "paper.json").exists():
        results["the README's line on where PPO diverges is the results'"] = readme_claim(
            out, args.write_readme, PPO_MARK, ppo_headline)
    if (out / "fair" / "trained_under_noise" / "paper_noise.json").exists():
        results["the README's line on the laws trained under noise is the results'"] = readme_claim(
            out, args.write_readme, NOISE_MARK, noise_headline)
    if (out / "reference" / "robustness.json").exists():
        results["the README's map headline is the results'"] = readme_claim(out, args.write_readme, MAP_MARK,
                                                                            map_headline)
    for name, (ok, detail) in results.items():
        print(f"{'PASS' if ok else 'FAIL'}  {name}: {detail}")
    ref_path = args.reference / "metrics.json"
    if ref_path.exists():
        ref = json.loads(ref_path.read_text())
        print(f"\nagainst {ref_path} (code {ref.get('meta', {}).get('provenance', {}).get('commit')}):")
        for s, c, k in KEY_NUMBERS:
            a, b = m.get(s, {}).get(c, {}).get(k), ref.get(s, {}).get(c, {}).get(k)
            if a is not None and b:
                print(f"  {s}/{c}/{k}: {a:.4g} (reference {b:.4g}, {100 * (a - b) / abs(b):+.1f} %)")
    prov = m.get("meta", {}).get("provenance", {})
    print(f"\nthis run: code {prov.get('commit')} (dirty: {prov.get('dirty')}), versions {prov.get('versions')}")
    return 0 if all(ok for ok, _ in results.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
