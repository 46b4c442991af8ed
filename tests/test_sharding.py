"""Devices: the default split of the host into one XLA device per core (``jaxtraffic.platform.devices``) and
batches sharded over the devices (``sim.sharding``): results independent of the device count."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxtraffic.platform import devices as _devices

REPO = Path(__file__).resolve().parents[1]


def test_split_host_rules(monkeypatch):
    monkeypatch.setattr(_devices, "host_cores", lambda: 4)
    monkeypatch.setattr(_devices, "_backends_initialised", lambda: True)
    on = {}  # the default: split
    assert _devices.split_host_devices(dict(on)) is None  # too late: jax already started
    monkeypatch.setattr(_devices, "_backends_initialised", lambda: False)
    assert _devices.split_host_devices({"JAXTRAFFIC_NO_DEVICE_SPLIT": "0"}) == 4  # "0" does not opt out
    env = dict(on)
    assert _devices.split_host_devices(env) == 4 and env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=4"
    env = {**on, "XLA_FLAGS": "--xla_cpu_foo=1"}
    assert _devices.split_host_devices(env) == 4 and env["XLA_FLAGS"].endswith("device_count=4")
    for env in ({**on, "XLA_FLAGS": "--xla_force_host_platform_device_count=3"},
                {**on, "JAXTRAFFIC_NO_DEVICE_SPLIT": "1"}, {**on, "JAX_NUM_CPU_DEVICES": "2"}):
        before = dict(env)
        assert _devices.split_host_devices(env) is None and env == before  # the user's choice wins
    monkeypatch.setattr(_devices, "host_cores", lambda: 1)
    assert _devices.split_host_devices(dict(on)) is None


IMPORTS = r"""
import json, os, sys
import jaxtraffic
library = os.environ.get("XLA_FLAGS", "")
import jax
n_library = jax.local_device_count() if sys.argv[1] == "library" else None
if sys.argv[1] == "cli":
    from jaxtraffic import cli
    n_cli = jax.local_device_count()
    print("RESULT " + json.dumps({"flags": library, "split": cli.DEVICE_SPLIT, "devices": n_cli}))
else:
    print("RESULT " + json.dumps({"flags": library, "devices": n_library}))
"""


@pytest.mark.parametrize("what", ["library", "cli"])
def test_import_jaxtraffic_leaves_the_devices_alone_and_the_command_lines_split(what):
    """``import jaxtraffic`` changes neither XLA_FLAGS nor the device count (a library user's process
    keeps jax's one CPU device); importing the command lines (``jaxtraffic.cli``) splits the host."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXTRAFFIC_NO_DEVICE_SPLIT",
                                                             "JAX_NUM_CPU_DEVICES")}
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", IMPORTS, what], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(next(x for x in out.stdout.splitlines() if x.startswith("RESULT "))[7:])
    assert res["flags"] == ""  # nothing set by import jaxtraffic
    cores = _devices.host_cores()
    if what == "library":
        assert res["devices"] == 1
    else:
        assert res["split"] == (cores if cores > 1 else None)
        assert res["devices"] == max(cores, 1)


CHILD = r"""
import json, sys
import jax, jax.numpy as jnp, numpy as np
import jaxtraffic
from jaxtraffic import TrafficParams, backstepping, lyapunov, simulate_batch, stack_params
p = TrafficParams(n_points=41, dt=0.5, max_delay_steps=8)
envs = stack_params(n_points=41, dt=0.5, max_delay_steps=8, delay=[0.0, 0.5, 1.0, 2.0, 3.0],
                    alpha=[0.5, 0.4, 0.6, 0.5, 0.3])
keys = jax.random.split(jax.random.PRNGKey(1), 5)
out = {"devices": jax.device_count()}
for name, c in (("lyap", lyapunov()), ("bs", backstepping(delay=2.0))):
    m = simulate_batch(envs, c, n_steps=60, keys=keys, nominal=p,
                       memory=jaxtraffic.Memory(chunk_size=2)).metrics
    out[name] = {k: np.asarray(v, np.float64).tolist() for k, v in m.items() if k != "diverged"}
print("RESULT " + json.dumps(out))
"""


def _child(env_extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAXTRAFFIC_NO_DEVICE_SPLIT")}
    env.update(env_extra, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(next(x for x in out.stdout.splitlines() if x.startswith("RESULT "))[7:])


@pytest.mark.slow
def test_batch_independent_of_device_count():
    one = _child({"JAXTRAFFIC_NO_DEVICE_SPLIT": "1"})
    two = _child({"XLA_FLAGS": "--xla_force_host_platform_device_count=2"})  # 5 envs: padded to 6
    assert one["devices"] == 1 and two["devices"] == 2
    for c in ("lyap", "bs"):
        for k, v in one[c].items():
            np.testing.assert_allclose(two[c][k], v, rtol=1e-6, atol=0, err_msg=f"{c} {k}")


def test_host_mesh_replicate_and_local_copy():
    """One process: a host-level call's mesh is every device, a traced call's this process's; the
    replicated placement and the local copy keep every value (and jax's dtype of each leaf)."""
    import jax
    import jax.numpy as jnp

    from jaxtraffic.sim import sharding

    mesh = sharding.host_mesh({"x": np.zeros(3)})
    assert mesh.size == len(jax.devices()) and not sharding.spans_processes(mesh)
    sizes = []
    jax.jit(lambda x: sizes.append(sharding.host_mesh(x).size) or x)(jnp.zeros(2))
    assert sizes == [len(jax.local_devices())]
    tree = {"a": np.arange(6.0).reshape(2, 3), "b": 3, "c": None}
    rep = sharding.replicate(tree, mesh)
    assert rep["c"] is None and rep["a"].dtype == jnp.float32 and rep["a"].sharding.is_fully_replicated
    assert len(rep["a"].sharding.device_set) == mesh.size
    back = sharding.local_copy(rep)
    np.testing.assert_array_equal(np.asarray(back["a"]), tree["a"])
    assert int(back["b"]) == 3 and len(back["a"].devices()) == 1
