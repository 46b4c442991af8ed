#!/usr/bin/env python
"""PPO reliability over seeds (issue 13): train ``train.py`` once per seed, evaluate each policy.

For every seed of ``--seeds`` (e.g. ``0-9`` or ``0,3,5``) it runs ``python train.py --seed S
--out-dir ROOT/seedS`` with the defaults plus any extra flags given after the script's own
(sequentially, one process per seed), then evaluates the run's saved policy
(``jaxtraffic.runs.policy.load_policy``: the best checkpoint, deterministic gains, acting on its own grid) on
the nonlinear plant ``--judge`` (the reference plant by default, else the paper's grid), paper initial
condition, plant delay D = 4 s, over 3000 steps (300 s) and 6000 steps (600 s), with
``backstepping(4.0)`` (on the paper's grid) over 300 s as the reference. A seed passes when

  (a) the run reached its stop rule (``summary.json``: ``stopped``, i.e. the rule held at
      ``--stop-patience`` consecutive evaluations),
  (b) final density L2 at 300 s < backstepping's,
  (c) J_comfort (300 s) <= 1.2 x backstepping's,
  (d) density L2 at 600 s < its value at 300 s (no slow growing mode),
  (e) on the reference plant: density L2 at 300 s and J_comfort change by < 10 % on the plant refined twice.

Times: ``first`` = trainer wall time when the stop rule first held (``seconds_to_stop_rule``;
from before initialisation, compilation included, Python/JAX import excluded), ``stop`` = trainer
wall time when the run stopped, ``proc`` = the process's wall time (imports included). The load
average is recorded before and after each run (the machine may be shared).

    python benchmarks/bench_ppo_seeds.py --seeds 0-9 --json
    python benchmarks/bench_ppo_seeds.py --seeds 0-3 --root /tmp/b -- --lr 3e-4   # extra train.py flags
    python benchmarks/bench_ppo_seeds.py --seeds 0-3 --root /tmp/b --eval-only    # re-evaluate runs
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from machine import cpu_model, load  # noqa: E402

J_RATIO_MAX = 1.2


def parse_seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part:
            lo, hi = part.split("-")
            out.extend(range(int(lo), int(hi) + 1))
        else:
            out.append(int(part))
    return out


def train_one(seed: int, run_dir: Path, extra: list[str], timeout: float | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, str(REPO / "train.py"), "--seed", str(seed), "--out-dir", str(run_dir), "--quiet", *extra]
    load0 = load()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"train.py failed for seed {seed}:\n{proc.stderr[-3000:]}")
    return {"proc_s": wall, "load_before": load0, "load_after": load(), "cmd": " ".join(cmd[1:])}


def plant_of(judge: str):
    """The plant a policy is judged on (D = 4 s): the paper's grid or the reference plant."""
    import jaxtraffic as jt

    return jt.TrafficParams(delay=4.0) if judge == "paper" else jt.TrafficParams.reference(delay=4.0)


def reference(judge: str = "paper"):
    import jaxtraffic as jt
    from jaxtraffic.control.adapter import adapt, baseline_grid

    p = plant_of(judge)
    res = jt.simulate(p, adapt(jt.backstepping(4.0), baseline_grid(p), p), n_steps=3000)
    return {"rho_L2_300": float(res.metrics["final_rho_L2"]), "J_comfort": float(res.metrics["J_comfort"])}


def evaluate_run(run_dir: Path, ref: dict, judge: str = "paper") -> dict:
    """The checks (a)-(d) on the plant ``judge`` (the policy acting on its own grid); on the reference plant
    also (e): density L2 at 300 s and J_comfort within 10 % on the plant refined twice (no chattering)."""
    import jaxtraffic as jt
    from jaxtraffic.runs import load_policy

    p = plant_of(judge)
    ctrl, _ = load_policy(run_dir, plant=p)
    m300 = jt.simulate(p, ctrl, n_steps=3000).metrics
    m600 = jt.simulate(p, ctrl, n_steps=6000).metrics
    summary = json.loads((run_dir / "summary.json").read_text())
    l2_300 = float(m300["final_rho_L2"])
    l2_600 = float(m600["final_rho_L2"])
    jc = float(m300["J_comfort"])
    diverged = bool(m300["diverged"]) or bool(m600["diverged"])
    stopped = bool(summary.get("stopped", summary.get("stop_rule_reached", False)))
    checks = {"stop": stopped, "L2": (not diverged) and l2_300 < ref["rho_L2_300"],
              "J": (not diverged) and jc <= J_RATIO_MAX * ref["J_comfort"], "600s": (not diverged) and l2_600 < l2_300}
    out = {"stopped": stopped, "first_s": summary.get("seconds_to_stop_rule"),
           "stop_s": summary.get("wall_s") if stopped else None, "env_steps": summary.get("env_steps"),
           "env_steps_first": summary.get("env_steps_to_stop_rule"), "rho_L2_300": l2_300, "rho_L2_600": l2_600,
           "J_comfort": jc, "J_ratio": jc / ref["J_comfort"], "diverged": diverged,
           "certified": (summary.get("certificate") or {}).get("stable")}
    if judge == "reference":
        fine = p.replace(n_points=2 * p.n_points - 1, substeps=2 * p.substeps)
        mf = jt.simulate(fine, load_policy(run_dir, plant=fine)[0], n_steps=3000).metrics
        out["refined_change_L2"] = float(mf["final_rho_L2"]) / l2_300 - 1.0
        out["refined_change_J"] = float(mf["J_comfort"]) / jc - 1.0
        checks["refined"] = max(abs(out["refined_change_L2"]), abs(out["refined_change_J"])) < 0.10
    return {**out, "checks": checks, "pass": all(checks.values())}


def _f(x, fmt):
    return "-" if x is None else format(x, fmt)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0-9", help="seeds: 0-9, 0,3,5, ...")
    ap.add_argument("--root", default="/tmp/bench_ppo_seeds", help="parent of the run directories seedS")
    ap.add_argument("--eval-only", action="store_true", help="evaluate existing run directories, do not train")
    ap.add_argument("--timeout", type=float, default=None, help="kill a training process after this many s")
    ap.add_argument("--json", action="store_true", help="print the results as JSON (after the table)")
    ap.add_argument("--judge", choices=("paper", "reference"), default="reference",
                    help="the plant the policies are judged on (default: the reference plant, which adds the "
                    "refinement check (e))")
    args, extra = ap.parse_known_args(argv)
    extra = [a for a in extra if a != "--"]
    seeds = parse_seeds(args.seeds)
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    import jax

    ref = reference(args.judge)
    print(f"backstepping(4.0): rho L2 at 300 s {ref['rho_L2_300']:.3f} veh/km, J_comfort {ref['J_comfort']:.0f}; "
          f"train.py extra flags: {' '.join(extra) or '(none)'}", flush=True)
    rows = []
    for s in seeds:
        run_dir = root / f"seed{s}"
        info = {} if args.eval_only else train_one(s, run_dir, extra, args.timeout)
        row = {"seed": s, **info, **evaluate_run(run_dir, ref, args.judge)}
        rows.append(row)
        print(f"seed {s}: {'PASS' if row['pass'] else 'fail'} stop {_f(row['stop_s'], '.1f')} s "
              f"L2 {row['rho_L2_300']:.3f}/{row['rho_L2_600']:.3f} J {row['J_ratio']:.2f}x "
              f"load {info.get('load_after', '-')}", flush=True)
    hdr = ("| seed | stop rule | first (s) | stop (s) | process (s) | env steps to stop | L2@300 (veh/km) | "
           "L2@600 | J_comfort | J / backstepping | pass | failed |")
    print("\n" + hdr + "\n|" + "---:|" * 12)
    for r in rows:
        failed = ",".join(k for k, ok in r["checks"].items() if not ok) or "-"
        print(f"| {r['seed']} | {'yes' if r['stopped'] else 'no'} | {_f(r['first_s'], '.1f')} | "
              f"{_f(r['stop_s'], '.1f')} | {_f(r.get('proc_s'), '.1f')} | {r['env_steps']} | {r['rho_L2_300']:.3f} | "
              f"{r['rho_L2_600']:.3f} | {r['J_comfort']:.0f} | {r['J_ratio']:.2f} | "
              f"{'yes' if r['pass'] else 'no'} | {failed} |")
    n_pass = sum(r["pass"] for r in rows)
    stops = [r["stop_s"] if r["stop_s"] is not None else float("inf") for r in rows]
    firsts = [r["first_s"] if r["first_s"] is not None else float("inf") for r in rows]
    med_stop, med_first = statistics.median(stops), statistics.median(firsts)
    out = {"seeds": seeds, "extra_flags": extra, "judge": args.judge, "reference": ref, "rows": rows,
           "n_pass": n_pass,
           "n_seeds": len(rows), "median_stop_s": med_stop, "median_first_s": med_first,
           "median_proc_s": statistics.median([r["proc_s"] for r in rows]) if rows and "proc_s" in rows[0] else None,
           "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "load_end": load(), "jax": jax.__version__,
                       "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())}}
    print(f"\n{n_pass} of {len(rows)} seeds pass; median time to stop {med_stop:.1f} s "
          f"(first met {med_first:.1f} s); load average at the end {load()}")
    if args.json:
        print(json.dumps(out, indent=2, default=lambda x: None if x == float("inf") else x))
    return out


if __name__ == "__main__":
    main()
