"""The accelerator benchmark (benchmarks/bench_accelerator.py, issue 48.4) runs on whatever backend JAX finds: here
the CPU, with tiny settings, in a subprocess (no platform forced), and reports positive rates for what it ran."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_accelerator_benchmark_runs_on_the_cpu():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop("JAX_PLATFORMS", None)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_accelerator.py"), "--batch-sizes", "8,16,8192",
           "--max-batch", "16", "--steps", "6", "--env-batches", "4", "--env-steps", "3", "--repeats", "1", "--json"]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert res["backend"] == "cpu"
    assert set(res["rollout_cell_updates_per_s"]) == {"8", "16"}  # 8192 is over the cap
    rates = [r for row in res["rollout_cell_updates_per_s"].values() for r in row.values()]
    assert len(rates) == 4 and all(r > 0 for r in rates)
    assert list(res["env_steps_per_s"]) == ["4"] and res["env_steps_per_s"]["4"] > 0
