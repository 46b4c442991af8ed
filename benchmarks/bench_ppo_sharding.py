#!/usr/bin/env python
"""PPO chunk time: the ``pmap`` trainer of an earlier revision vs the current ``jit`` + ``shard_map`` one.

Both build ``(init, train_chunk)`` for the same config (default ``train.py`` settings unless flags
say otherwise) in one process, compile, then time ``--chunks`` chunks each, interleaved (pmap,
shard_map, pmap, ...) so that a changing machine load hits both alike. Wall and process-CPU seconds
per chunk are reported (best and median), and whether the two runners agree bit for bit. The
pmap version is ``jaxtraffic/learn/ppo/algorithm.py`` at ``--pmap-rev`` (git show), imported as a module of
its own; it shares the rest of the library with the working tree.

    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/bench_ppo_sharding.py --chunks 4
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import jax  # noqa: E402
import numpy as np  # noqa: E402
from machine import cpu_model, load  # noqa: E402  (benchmarks/machine.py)

from jaxtraffic.learn import ppo  # noqa: E402
from jaxtraffic.learn.env import TrafficEnv  # noqa: E402
from jaxtraffic.runs.config import TrainConfig  # noqa: E402
from jaxtraffic.runs.ppo.trainer import build  # noqa: E402


def pmap_module(rev: str):
    """``jaxtraffic/learn/ppo/algorithm.py`` of git revision ``rev`` as the module ``ppo_pmap``."""
    src = subprocess.run(["git", "show", f"{rev}:jaxtraffic/learn/ppo/algorithm.py"], cwd=REPO, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "ppo_pmap.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("ppo_pmap", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pmap-rev", default="ffaad65", help="git revision whose ppo.py still uses pmap")
    ap.add_argument("--chunks", type=int, default=4, help="timed chunks per version (after the compiling one)")
    ap.add_argument("--num-envs", type=int, default=None, help="default: train.py's")
    args = ap.parse_args()
    s = TrainConfig() if args.num_envs is None else TrainConfig.make(ppo={"num_envs": args.num_envs})
    cfg, env_params = build(s)
    old = pmap_module(args.pmap_rev)
    versions = {}
    out = {"machine": cpu_model(), "devices": jax.device_count(), "jax": jax.__version__,
           "num_envs": cfg.num_envs, "steps_per_chunk": cfg.steps_per_update * cfg.updates_per_chunk,
           "load_start": load()}
    for name, mod in (("pmap", old), ("shard_map", ppo)):
        init, chunk = mod.make_train(cfg, env_params, env=TrafficEnv)
        t0 = time.perf_counter()
        runner = jax.block_until_ready(init(jax.random.PRNGKey(0)))
        runner, m = jax.block_until_ready(chunk(runner))
        out[f"{name}_compile_and_first_chunk_s"] = round(time.perf_counter() - t0, 2)
        versions[name] = {"chunk": chunk, "runner": runner, "wall": [], "cpu": []}
    for _ in range(args.chunks):
        for v in versions.values():
            t0, c0 = time.perf_counter(), time.process_time()
            v["runner"], _ = jax.block_until_ready(v["chunk"](v["runner"]))
            v["wall"].append(time.perf_counter() - t0)
            v["cpu"].append(time.process_time() - c0)
    for name, v in versions.items():
        for k in ("wall", "cpu"):
            out[f"{name}_{k}_s_best"] = round(min(v[k]), 3)
            out[f"{name}_{k}_s_median"] = round(statistics.median(v[k]), 3)
    out["wall_ratio_shard_map_over_pmap"] = round(out["shard_map_wall_s_median"] / out["pmap_wall_s_median"], 3)
    la, lb = (jax.tree_util.tree_leaves(jax.device_get(v["runner"])) for v in versions.values())
    out["bit_identical"] = all(np.array_equal(a, b, equal_nan=True) for a, b in zip(la, lb, strict=True))
    out["load_end"] = load()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
