#!/usr/bin/env python
"""Gradient-based training: time to beat backstepping, determinism, delay range, memory.

    python benchmarks/bench_learning.py [--json] [--repeats 2] [--skip-memory]

Parts (each in a fresh subprocess, so compile times are included and peak memory is per part):
  1. constant gains (``train.py gradient --policy gains``, defaults), ``--repeats`` times:
     wall time (compilation included) until the evaluation first beats ``backstepping(4)`` at
     D = 4 s on both final density L2 and J_comfort, and whether the repeats end bit-identical;
  2. the neural policy (``--policy network``): the same, and the final policy on plant delays
     0-6 s (600 s, paper initial condition): diverged? final density L2;
  3. memory: peak RSS (VmHWM) of one gradient step over 64 scenarios x 3000 steps (gains
     policy), with and without gradient checkpointing (without: 8 scenarios, to stay safe).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import cpu_model, load  # noqa: E402

MEMORY_SNIPPET = r"""
import resource, sys, time, jax, jax.numpy as jnp
from jaxtraffic import TrafficParams
from jaxtraffic.learn.gradient import objective
remat, n_d, n_a = sys.argv[1] == "1", int(sys.argv[2]), int(sys.argv[3])
cfg = objective.GradientConfig(train_delays=tuple(float(d) for d in range(n_d)),
                               train_alphas=tuple(0.05 + 0.5 * i / max(1, n_a - 1) for i in range(n_a)),
                               train_horizon_s=300.0)
base = TrafficParams(delay=4.0)
scen, w = objective.training_scenarios(cfg, base), objective.weights_of(cfg)
f = jax.jit(jax.grad(lambda t: objective.objective(t, scen, w, cfg, base, remat=remat)[0]))
theta = jnp.asarray([-0.3, -0.6, -0.6])
jax.block_until_ready(f(theta))
t0 = time.perf_counter(); jax.block_until_ready(f(theta)); t = time.perf_counter() - t0
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"{cfg.n_scenarios} {int(hwm) / 1024:.0f} {t:.2f}")
"""

DELAY_SNIPPET = r"""
import json, sys
import jaxtraffic as jt
from jaxtraffic.runs import load_policy
c, _ = load_policy(sys.argv[1])
out = {}
for d in range(7):
    m = jt.simulate(jt.TrafficParams(delay=float(d)), c, n_steps=6000, nominal=jt.TrafficParams(delay=4.0)).metrics
    out[d] = {"diverged": bool(m["diverged"]), "final_rho_L2_veh_km": float(m["final_rho_L2"])}
print(json.dumps(out))
"""


def train(policy: str, out: Path) -> dict:
    subprocess.run([sys.executable, str(ROOT / "train.py"), "gradient", "--policy", policy,
                    "--out-dir", str(out), "--quiet"], check=True, cwd=ROOT)
    summary = json.loads((out / "summary.json").read_text())
    summary["checkpoint_bytes"] = (out / "checkpoint.msgpack").read_bytes()
    return summary


def part_training(policy: str, repeats: int, tmp: Path) -> dict:
    runs = [train(policy, tmp / f"{policy}{i}") for i in range(repeats)]
    ev, ref = runs[0]["final_eval"], runs[0]["backstepping_eval"]
    res = {
        "seconds_to_beat_backstepping": [r["seconds_to_beat_backstepping"] for r in runs],
        "wall_s": [r["wall_s"] for r in runs], "updates": runs[0]["updates"],
        "final_rho_L2_veh_km": ev["final_rho_L2"], "final_J_comfort": ev["J_comfort"],
        "backstepping_rho_L2_veh_km": ref["final_rho_L2"], "backstepping_J_comfort": ref["J_comfort"],
        "repeats_bit_identical": all(r["checkpoint_bytes"] == runs[0]["checkpoint_bytes"] for r in runs),
    }
    if policy == "network":
        out = subprocess.run([sys.executable, "-c", DELAY_SNIPPET, str(tmp / f"{policy}0")], check=True,
                             capture_output=True, text=True, cwd=ROOT).stdout
        res["delays_0_6"] = json.loads(out.strip().splitlines()[-1])
    return res


def part_memory() -> list[dict]:
    rows = []
    for remat, nd, na in ((True, 8, 8), (False, 8, 1)):
        out = subprocess.run([sys.executable, "-c", MEMORY_SNIPPET, str(int(remat)), str(nd), str(na)], check=True,
                             capture_output=True, text=True, cwd=ROOT).stdout.split()
        rows.append({"remat": remat, "scenarios": int(out[0]), "steps": 3000, "peak_rss_mib": float(out[1]),
                     "grad_s": float(out[2])})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--skip-memory", action="store_true")
    args = ap.parse_args()
    result = {"machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "load_start": load()}}
    with tempfile.TemporaryDirectory() as d:
        for policy in ("gains", "network"):
            result[policy] = part_training(policy, args.repeats, Path(d))
    if not args.skip_memory:
        result["memory"] = part_memory()
    result["machine"]["load_end"] = load()
    if args.json:
        print(json.dumps(result, indent=2))
        return
    for policy in ("gains", "network"):
        r = result[policy]
        print(f"{policy:8s} beat backstepping after {r['seconds_to_beat_backstepping']} s (wall {r['wall_s']}); "
              f"final rho L2 {r['final_rho_L2_veh_km']:.3f} vs {r['backstepping_rho_L2_veh_km']:.3f} veh/km, "
              f"J_comfort {r['final_J_comfort']:.0f} vs {r['backstepping_J_comfort']:.0f}; "
              f"repeats bit-identical: {r['repeats_bit_identical']}")
    if "delays_0_6" in result["network"]:
        print("network, plant delays 0-6 s (600 s):", {d: (v["diverged"], round(v["final_rho_L2_veh_km"], 3))
                                                        for d, v in result["network"]["delays_0_6"].items()})
    for m in result.get("memory", []):
        print(f"memory: remat={m['remat']} {m['scenarios']} scenarios x {m['steps']} steps: peak RSS "
              f"{m['peak_rss_mib']:.0f} MiB, one gradient {m['grad_s']:.2f} s")
    print("machine:", result["machine"])


if __name__ == "__main__":
    main()
