"""Multi-process gradient training and evaluation (``jaxtraffic.platform.distributed``): 2 processes on
localhost (CPU, gloo, one device each) against one process with 2 devices, on a tiny problem.

Each child runs ``train.py gradient`` (a network policy, 3 scenarios: an odd count, so the
split over 2 devices pads), then ``--resume`` to twice the Adam steps, then ``evaluate.py`` on that
run. In each pair process 1 is given its own output directories for the fresh run and the
evaluation: they must not be created (only process 0 writes); the resume reads process 0's run
directory on both (a shared file system). The checkpoint, the learning curve and metrics.json must
agree with the 2-device run to float tolerance: the same scenarios and rollouts split over the
same two devices, whatever process holds them.
"""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import jax
import numpy as np
import pytest
from test_multihost import _finish, _free_port, _gloo
from tiny_runs import REPO, xla_env

from jaxtraffic.runs import checkpoint as ckpt

CHILD = r"""
import json, sys
sys.path.insert(0, ".")
import evaluate, train
cluster, first, run, out = json.loads(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
grad = ["gradient", "--policy", "network", "--n-points", "21", "--train-delays", "1,2,3",
        "--train-horizon-s", "4", "--steps-per-chunk", "1", "--eval-horizon-s", "4", "--quiet"]
train.main(grad + cluster + ["--out-dir", first, "--grad-steps", "2"])
train.main(grad + cluster + ["--out-dir", run, "--grad-steps", "4", "--resume"])
evaluate.main(cluster + ["--run", run, "--out", out, "--horizon", "4", "--noise-seeds", "2", "--robust-grid", "3x2",
                         "--robust-horizon", "4", "--gradient", "none", "--plants", "paper", "--no-numerics-check",
                         "--fair", "0"])
import jax, numpy as np
from jaxtraffic.sim.sharding import host_mesh, spans_processes
mesh = host_mesh(np.zeros(2))  # what a host-level batched call splits over
print("RESULT " + json.dumps({"process": jax.process_index(), "processes": jax.process_count(),
                              "devices": jax.device_count(), "local": jax.local_device_count(),
                              "mesh": mesh.size, "spans": spans_processes(mesh)}))
"""


def _start(cluster: list[str], first, run, out, **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(cluster), str(first), str(run), str(out)],
                            cwd=REPO, env=xla_env(**env), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _numbers(obj, path=""):
    """(path, value) of every finite float in a metrics.json tree, but for timings and provenance."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k not in ("meta", "runtime_s", "wall_s"):
                yield from _numbers(v, f"{path}/{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, f"{path}[{i}]")
    elif isinstance(obj, float) and math.isfinite(obj):
        yield path, obj


@pytest.mark.slow
@pytest.mark.cluster
@pytest.mark.skipif(not _gloo(), reason="this jaxlib has no gloo CPU collectives")
def test_gradient_training_and_evaluation_in_two_processes(tmp_path):
    port = _free_port()
    cluster = ["--coordinator-address", f"127.0.0.1:{port}", "--num-processes", "2"]
    pair = [_start([*cluster, "--process-id", str(i)], tmp_path / f"first{i}", tmp_path / "first0",
                   tmp_path / f"out{i}", JAXTRAFFIC_NO_DEVICE_SPLIT="1") for i in (0, 1)]
    ref = _start([], tmp_path / "ref", tmp_path / "ref", tmp_path / "out_ref",
                 flags=["--xla_force_host_platform_device_count=2"])
    res = [_finish(p, timeout=400) for p in pair]
    assert [r["process"] for r in res] == [0, 1]
    assert all(r["processes"] == 2 and r["devices"] == 2 and r["local"] == 1 for r in res)
    assert all(r["mesh"] == 2 and r["spans"] for r in res)  # the batches were split across the processes
    r1 = _finish(ref, timeout=400)
    assert r1["devices"] == r1["mesh"] == 2 and not r1["spans"]
    assert not (tmp_path / "first1").exists() and not (tmp_path / "out1").exists()  # process 1 wrote nothing

    multi, one = tmp_path / "first0", tmp_path / "ref"
    assert sorted(p.name for p in multi.iterdir()) == sorted(p.name for p in one.iterdir())
    (state_m, meta_m), (state_1, meta_1) = ckpt.load_checkpoint(multi), ckpt.load_checkpoint(one)
    assert meta_m["updates"] == meta_1["updates"] == 4
    lm, l1 = jax.tree_util.tree_leaves(state_m), jax.tree_util.tree_leaves(state_1)
    assert len(lm) == len(l1) > 3
    for a, b in zip(lm, l1, strict=True):
        np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-5, atol=1e-6)
    with open(multi / "learning_curve.csv", newline="") as f:
        rows_m = list(csv.DictReader(f))
    with open(one / "learning_curve.csv", newline="") as f:
        rows_1 = list(csv.DictReader(f))
    assert len(rows_m) == len(rows_1) == 4
    for rm, r1 in zip(rows_m, rows_1, strict=True):
        for k in rm:
            if k != "wall_s":
                np.testing.assert_allclose(float(rm[k]), float(r1[k]), rtol=1e-5, atol=1e-6, err_msg=k)

    out_m, out_1 = tmp_path / "out0", tmp_path / "out_ref"
    assert sorted(p.name for p in out_m.iterdir()) == sorted(p.name for p in out_1.iterdir())
    mm, m1 = (dict(_numbers(json.loads((d / "metrics.json").read_text()))) for d in (out_m, out_1))
    assert mm.keys() == m1.keys() and len(mm) > 100
    for k in mm:
        np.testing.assert_allclose(mm[k], m1[k], rtol=1e-4, atol=1e-7, err_msg=k)
    rob_m, rob_1 = (json.loads((d / "robustness.json").read_text())["controllers"] for d in (out_m, out_1))
    assert rob_m.keys() == rob_1.keys() and len(rob_1) >= 4
    for c in rob_1:
        for k in rob_1[c]:
            np.testing.assert_allclose(np.asarray(rob_m[c][k], float), np.asarray(rob_1[c][k], float),
                                       rtol=1e-4, atol=1e-7, err_msg=f"{c} {k}")
