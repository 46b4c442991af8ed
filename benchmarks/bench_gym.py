#!/usr/bin/env python
"""Env steps/s of the Gymnasium vector env (``jaxtraffic.ecosystem.gym_env.GainVectorEnv``).

    python benchmarks/bench_gym.py                       # 16, 256, 1024 envs, the training grid (201 points)
    python benchmarks/bench_gym.py --num-envs 16 256 --n-points 51 --steps 200 --json

What a Gymnasium / SB3 user gets per ``step`` call: numpy actions in, one jit-compiled vmapped
``learn.env.step_env`` over the batch, numpy observations, rewards, flags and infos out (the
same-step autoreset included: episodes of ``--horizon-s``). Random actions in [-1, 1]^3, drawn
beforehand. Compilation is excluded (a warm-up of 5 steps); best and median of ``--repeats`` timed
runs of ``--steps`` steps, and env steps per second of process CPU time (all threads; less
sensitive to other jobs on shared cores). Needs gymnasium (``pip install -e ".[gym]"``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np


def bench(num_envs: int, steps: int, repeats: int, **config) -> dict:
    from jaxtraffic.ecosystem.gym_env import GainVectorEnv

    venv = GainVectorEnv(num_envs, **config)
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, num_envs, 3)).astype(np.float32)
    for a in actions[:5]:  # compile
        venv.step(a)
    rates, cpu_rates = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for a in actions:
            venv.step(a)
        rates.append(steps * num_envs / (time.perf_counter() - t0))
        cpu_rates.append(steps * num_envs / max(1e-9, time.process_time() - c0))
    venv.close()
    return {"num_envs": num_envs, "steps": steps, "best": max(rates), "median": statistics.median(rates),
            "per_cpu_s": max(cpu_rates)}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--num-envs", type=int, nargs="+", default=[16, 256, 1024])
    ap.add_argument("--n-points", type=int, default=201)
    ap.add_argument("--horizon-s", type=float, default=100.0)
    ap.add_argument("--steps", type=int, default=300, help="steps per timed run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    import jax

    out = []
    load0 = os.getloadavg()[0]
    for n in args.num_envs:
        out.append(bench(n, args.steps, args.repeats, n_points=args.n_points, horizon_s=args.horizon_s))
    meta = {"n_points": args.n_points, "jax": jax.__version__, "backend": jax.default_backend(),
            "load_avg_start": round(load0, 2), "load_avg_end": round(os.getloadavg()[0], 2)}
    if args.json:
        print(json.dumps({"meta": meta, "results": out}))
    else:
        print(f"GainVectorEnv, {meta}")
        print("| envs | env steps/s (best) | env steps/s (median) | env steps per CPU-s |\n|---:|---:|---:|---:|")
        for r in out:
            print(f"| {r['num_envs']} | {r['best']:,.0f} | {r['median']:,.0f} | {r['per_cpu_s']:,.0f} |")
    return out


if __name__ == "__main__":
    main()
