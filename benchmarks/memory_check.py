"""The run's memory estimate (``runs.config.checks.memory_estimate``) against the peak memory of tiny PPO trainings
that stress one component each (the delay buffer, the network): prints both, GiB.

    python benchmarks/memory_check.py            # about 1 minute on 2 cores, up to ~6 GiB of memory
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASE = {"plant": {"n_points": 201, "delay": 0.5}, "ppo": {"num_envs": 4, "num_seeds": 1, "num_steps": 8,
        "num_minibatches": 2, "update_epochs": 2, "updates_per_chunk": 2}, "run": {"val_horizon_s": 2.0}}
CASES = {"bare": {}, "delay buffer 50 000 steps": {"plant": {"max_delay_steps": 50000}},
         "network (4000, 4000)": {"ppo": {"hidden": [4000, 4000]}}}
CHILD = """
import json, resource, sys
from jaxtraffic.cli import train
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.checks import memory_estimate
tables = json.loads(sys.argv[1])
flags = ["--quiet", "--total-steps", "64", "--horizon-s", "3", "--eval-horizon-s", "2", "--out-dir", sys.argv[2]]
for section, fields in tables.items():
    for k, v in fields.items():
        flags += [f"--{k.replace('_', '-')}", *map(str, v if isinstance(v, list) else [v])]
est = sum(memory_estimate(TrainConfig.make(**tables)).values()) / 2**30
try:
    train.main(flags)
except SystemExit:
    pass
print(json.dumps({"estimate": est, "peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}))
"""


def measure(tables: dict) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(tables), f"{tmp}/run"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    rows = {}
    for name, extra in CASES.items():
        tables = {k: {**v, **extra.get(k, {})} for k, v in BASE.items()}
        rows[name] = measure(tables)
    bare = rows["bare"]["peak"]
    print(f"{'case':28s} {'estimate GiB':>12s} {'measured GiB (peak less bare)':>30s}")
    for name, r in rows.items():
        print(f"{name:28s} {r['estimate']:12.3f} {r['peak'] - bare:30.3f}")


if __name__ == "__main__":
    main()
