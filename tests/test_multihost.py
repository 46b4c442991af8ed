"""Multi-process PPO training (``jaxtraffic.platform.distributed``): 2 processes on localhost (CPU, gloo, one
device each) against one process with 2 devices, on a tiny problem.

Each child runs ``train.py``'s ``main`` twice: a fresh run of 1 chunk, then ``--resume`` to 2 chunks
(one compiled program, as in ``tiny_runs.TWO_DEVICES``). In the fresh run each process of the pair
is given its own ``--out-dir``: process 1's must not be created (only process 0 writes); the resume
reads process 0's directory on both (a shared file system). The curve and the checkpoint must
agree with the 2-device run to float tolerance.
"""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from tiny_runs import REPO, TINY, xla_env

from jaxtraffic.platform import distributed
from jaxtraffic.runs import checkpoint as ckpt

CHILD = r"""
import json, sys
sys.path.insert(0, ".")
import train
from jaxtraffic.learn.ppo import algorithm as ppo

orig, cache = ppo.make_train, {}
def shared(cfg, env_params, devices=None, *, env):  # the resume reuses the compiled program
    key = (cfg, env_params, env)
    cache[key] = cache.get(key) or orig(cfg, env_params, devices, env=env)
    return cache[key]
ppo.make_train = shared
argv, first_dir, run_dir = json.loads(sys.argv[1]), sys.argv[2], sys.argv[3]
train.main(argv + ["--out-dir", first_dir, "--total-steps", "64", "--keep-going"])
train.main(argv + ["--out-dir", run_dir, "--total-steps", "128", "--keep-going", "--resume"])
import jax
print("RESULT " + json.dumps({"process": jax.process_index(), "processes": jax.process_count(),
                              "devices": jax.device_count(), "local": jax.local_device_count()}))
"""

ARGV = [*TINY, "--val-horizon-s", "0"]  # no validation suite: a shorter compile


def test_settings_from_flags_or_environment():
    env = {"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234", "JAX_NUM_PROCESSES": "4", "JAX_PROCESS_ID": "3"}
    assert distributed.settings(env={}) is None  # one process: nothing to start
    assert distributed.settings(env=env) == {"coordinator_address": "10.0.0.1:1234", "num_processes": 4,
                                             "process_id": 3}
    assert distributed.settings("h:1", 2, 0, env=env) == {"coordinator_address": "h:1", "num_processes": 2,
                                                          "process_id": 0}  # flags win
    with pytest.raises(ValueError, match="--process-id"):
        distributed.settings("h:1", 2, env={})
    for n, i in ((2, 2), (0, 0), (2, -1)):
        with pytest.raises(ValueError, match="process_id"):
            distributed.settings("h:1", n, i, env={})
    with pytest.raises(ValueError, match="integers"):
        distributed.settings(env={**env, "JAX_NUM_PROCESSES": "two"})


def _gloo() -> bool:
    try:
        from jaxlib import _jax
    except ImportError:
        return False
    return hasattr(_jax, "make_gloo_tcp_collectives")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(argv: list[str], first: str, run: str, **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(argv), first, run], cwd=REPO, env=xla_env(**env),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 240) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"timed out:\n{err[-3000:]}")
    assert proc.returncode == 0, err[-3000:]
    return json.loads(next(x for x in out.splitlines() if x.startswith("RESULT "))[7:])


def _rows(run) -> list[dict]:
    with open(run / "learning_curve.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
@pytest.mark.cluster
@pytest.mark.skipif(not _gloo(), reason="this jaxlib has no gloo CPU collectives")
def test_two_processes_match_two_devices(tmp_path):
    port = _free_port()
    pair = [_start([*ARGV, "--coordinator-address", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id",
                    str(i)], str(tmp_path / f"first{i}"), str(tmp_path / "first0"), JAXTRAFFIC_NO_DEVICE_SPLIT="1")
            for i in (0, 1)]
    ref = _start(ARGV, str(tmp_path / "ref"), str(tmp_path / "ref"),
                 flags=["--xla_force_host_platform_device_count=2"])
    res = [_finish(p) for p in pair]
    assert [r["process"] for r in res] == [0, 1]
    assert all(r["processes"] == 2 and r["devices"] == 2 and r["local"] == 1 for r in res)
    assert _finish(ref)["devices"] == 2
    assert not (tmp_path / "first1").exists()  # process 1 wrote nothing
    multi, one = tmp_path / "first0", tmp_path / "ref"
    assert sorted(p.name for p in multi.iterdir()) == sorted(p.name for p in one.iterdir())
    rows_m, rows_1 = _rows(multi), _rows(one)
    assert len(rows_m) == len(rows_1) == 2
    for rm, r1 in zip(rows_m, rows_1, strict=True):
        for k in rm:
            if k != "wall_s":
                np.testing.assert_allclose(float(rm[k]), float(r1[k]), rtol=1e-5, atol=1e-6, err_msg=k)
    state_m, meta_m = ckpt.load_checkpoint(multi)
    state_1, meta_1 = ckpt.load_checkpoint(one)
    assert meta_m["env_steps"] == meta_1["env_steps"] == 128
    for name in ("params", "opt_state", "stats", "obs"):
        lm, l1 = jax.tree_util.tree_leaves(state_m[name]), jax.tree_util.tree_leaves(state_1[name])
        assert len(lm) == len(l1) > 0
        for a, b in zip(lm, l1, strict=True):
            assert np.shape(a) == np.shape(b) and np.shape(a)[0] == 2, name  # the device axis
            np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=1e-5, atol=1e-6,
                                       err_msg=name)
