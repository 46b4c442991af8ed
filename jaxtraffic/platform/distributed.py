"""Multi-process (multi-host) runs: ``jax.distributed`` set up from flags or environment variables.

One program runs as N processes (JAX's multi-controller model); each sees every device of every
process in ``jax.devices()`` and its own in ``jax.local_devices()``. ``initialize`` must run before
any JAX computation (``train.py`` calls it first). The coordinator address, process count and
process id come from the arguments (``--coordinator-address HOST:PORT --num-processes N
--process-id I``) or else from ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and
``JAX_PROCESS_ID``; with none of them set, nothing is done (one process). On the CPU backend the
collectives go through gloo (``jax_cpu_collectives_implementation``; the setting only concerns CPU
devices, so it is made on every platform).

What runs across processes: every host-level batched rollout (``simulate_batch`` with concrete
inputs, hence the evaluation, the trainers' evaluations and validation suites) is split over every
device of every process and its result gathered into every process (``sim.sharding``); the PPO
trainer's mesh spans ``jax.devices()`` (gradients and statistics averaged over every device); the
gradient trainer splits its scenarios over them. The decisions (stop, budget, signals) are process
0's (``agree``), and only process 0 prints and writes files (``is_writer``). Every process runs
the same program on the same inputs (SPMD) and must see the run directories (a shared file system).

The command lines split each process's host into one CPU device per core: with N processes
on one machine set ``JAXTRAFFIC_NO_DEVICE_SPLIT=1`` (one device each) so the devices do not
oversubscribe the cores.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np
import numpy.typing as npt
from jax.experimental import multihost_utils

ENV = {"coordinator_address": "JAX_COORDINATOR_ADDRESS", "num_processes": "JAX_NUM_PROCESSES",
       "process_id": "JAX_PROCESS_ID"}

__all__ = ["ENV", "agree", "barrier", "initialize", "is_writer", "put_like", "settings",
           "to_host"]


def settings(coordinator_address: str | None = None, num_processes: int | None = None,
             process_id: int | None = None, env: Mapping[str, str] | None = None) -> dict | None:
    """The arguments of ``jax.distributed.initialize`` from the given values, else ``env`` (default
    ``os.environ``); None when nothing asks for several processes. ``ValueError`` when incomplete."""
    env = os.environ if env is None else env
    given = {"coordinator_address": coordinator_address, "num_processes": num_processes, "process_id": process_id}
    out = {k: v if v is not None else env.get(ENV[k]) or None for k, v in given.items()}
    if all(v is None for v in out.values()):
        return None
    missing = [f"--{k.replace('_', '-')} (${ENV[k]})" for k, v in out.items() if v is None]
    if missing:
        raise ValueError(f"a multi-process run needs the coordinator address, process count and id; missing: "
                         f"{', '.join(missing)}")
    num, pid = out["num_processes"], out["process_id"]
    assert num is not None and pid is not None  # (none missing)
    try:
        n, i = int(num), int(pid)
    except ValueError:
        raise ValueError(f"num_processes and process_id must be integers, got {out['num_processes']!r}, "
                         f"{out['process_id']!r}") from None
    if n < 1 or not 0 <= i < n:
        raise ValueError(f"need num_processes >= 1 and 0 <= process_id < num_processes, got {n}, {i}")
    return {"coordinator_address": str(out["coordinator_address"]), "num_processes": n, "process_id": i}


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> bool:
    """Start ``jax.distributed`` when asked (see ``settings``; once per process); True if this is a
    multi-process run. Call it before any JAX computation."""
    kwargs = settings(coordinator_address, num_processes, process_id)
    if kwargs is None:
        return False
    if jax.distributed.is_initialized():  # a second run in the same processes
        return True
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**kwargs)
    return True


def is_writer() -> bool:
    """Whether this process writes the outputs (process 0)."""
    return jax.process_index() == 0


def put_like(template: Any, host: Any) -> Any:
    """``host`` (numpy arrays holding global values) placed like ``template``'s leaves, arrays that
    span processes included (each process fills its own shards)."""
    def one(t, x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, t.sharding, lambda index: x[index])
    return jax.tree.map(one, template, host)


def to_host(tree: Any) -> Any:
    """Every leaf as a numpy array holding its global value (collective when arrays span processes:
    every process must call it)."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.process_allgather(tree, tiled=True)


def agree(local: npt.ArrayLike) -> np.ndarray:
    """Every process's ``local`` (a small integer vector), stacked along a new first axis (process
    order); a collective, so every process must call it at the same point."""
    local = np.asarray(local, np.int32)
    if jax.process_count() == 1:
        return local[None]
    return np.asarray(multihost_utils.process_allgather(local, tiled=False))


def barrier(name: str) -> None:
    """Wait until every process has reached ``barrier(name)`` (nothing to wait for in one process)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
