#!/usr/bin/env python
"""What a program loses without the device split: batched rollouts on one XLA CPU device (what
``import jaxtraffic`` alone gives) against one device per core (``jaxtraffic.split_host_devices()``,
which the command lines call).

Runs ``bench_sim.py --json`` in fresh processes (the device count is fixed when jax starts), the two
settings interleaved ``--rounds`` times, and prints each setting's best throughput and their ratio
(split / one device) per batch size: a ratio measured side by side, which a noisy machine bends less
than either figure.

    python benchmarks/bench_device_split.py                     # batches 64 and 1024, 600 steps
    python benchmarks/bench_device_split.py --batch-sizes 256 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _bench(devices: int, args: argparse.Namespace) -> dict[int, float]:
    cmd = [sys.executable, str(HERE / "bench_sim.py"), "--json", "--no-memory", "--controllers", "lyapunov",
           "--batch-sizes", args.batch_sizes, "--steps", str(args.steps), "--repeats", "3", "--devices", str(devices)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    rows = json.loads(out.stdout[out.stdout.index("{"):])["throughput"]
    return {int(r["batch"]): float(r["env_steps_per_s"]) for r in rows}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch-sizes", default="64,1024")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--rounds", type=int, default=2, help="interleaved runs of each setting")
    args = ap.parse_args(argv)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    best: dict[int, dict[int, float]] = {1: {}, cores: {}}
    for _ in range(args.rounds):
        for devices in best:
            for batch, rate in _bench(devices, args).items():
                best[devices][batch] = max(rate, best[devices].get(batch, 0.0))
    print(f"{cores} cores; Lyapunov rollouts at 201 points, {args.steps} steps, best of {args.rounds} x 3 calls")
    print("batch | one device (env steps/s) | one per core (env steps/s) | ratio")
    for batch in sorted(best[1]):
        one, split = best[1][batch], best[cores][batch]
        print(f"{batch:5d} | {one:12,.0f} | {split:12,.0f} | {split / one:.2f}x")


if __name__ == "__main__":
    main()
