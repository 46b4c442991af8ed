"""Batches split over devices: one code path for one device, many devices and many processes.

``sharded_batch(fn, args, axes, mesh)`` runs ``fn`` (a function of a batch) with its batch axis
split over a one-axis ``Mesh`` (``shard_map``: each device runs ``fn`` on its share; no
communication). The default mesh is this process's devices, ``jax.local_devices()``, which is
what a call traced inside a user's ``jit`` gets. A host-level batched call (``simulate_batch`` with
concrete inputs, the gradient trainer) takes ``host_mesh``: in a multi-process run
(``jaxtraffic.platform.distributed``) that is every device of every process, its inputs are placed
``replicate``-d on every device, its outputs are gathered into every process inside the same
program (a replicated output), and ``local_copy`` hands each process ordinary local arrays. So N
processes share the work of one batch and all of them see the whole result; every process must
make the same calls in the same order (SPMD). Entries are dealt out like cards (entry i to device i mod
n_devices, in order), so that a batch ordered by cost (the robustness map, by delay) loads every device alike
and each device's share keeps the order. A batch that is not a multiple of the device count is
padded with copies of its last entry, whose results are dropped. Entries are independent, so a
result depends on the device count only through the per-device batch size XLA compiles for
(float rounding only: a vectorised and a scalar loop may round differently; tests/test_sharding.py
checks 1 vs 2 devices to rtol 1e-6 in float32).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxtraffic.platform.tracing import is_traced

AXIS = "batch"

__all__ = ["AXIS", "batch_mesh", "batch_sharding", "gathered", "host_mesh", "local_copy", "replicate",
           "sharded_batch", "spans_processes"]


def batch_mesh(devices: list | None = None) -> Mesh:
    """A one-axis mesh (``AXIS``) over ``devices`` (default: this process's, ``jax.local_devices()``)."""
    return Mesh(np.array(jax.local_devices() if devices is None else devices), (AXIS,))


def spans_processes(mesh: Mesh) -> bool:
    """Whether ``mesh`` holds devices of more than one process."""
    return len({d.process_index for d in mesh.devices.flat}) > 1


def host_mesh(tree: Any = None) -> Mesh:
    """The mesh of a host-level batched call on ``tree`` (its inputs): every device of every process
    (``jax.devices()``) unless ``tree`` holds a tracer (a call inside a user's transformation, which
    stays on this process's devices)."""
    return batch_mesh(None if is_traced(tree) else list(jax.devices()))


def replicate(tree: Any, mesh: Mesh) -> Any:
    """Every array leaf of ``tree`` (identical on every process: SPMD) placed whole on every device of
    ``mesh``, devices of other processes included (each process fills its own)."""
    sharding = NamedSharding(mesh, PartitionSpec())

    def one(x):
        x = np.asarray(x)
        x = x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False)  # float32 unless x64, as jax gives it
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree.map(one, tree)


def gathered(tree: Any, mesh: Mesh) -> Any:
    """Inside a traced function: ``tree`` whole on every device of ``mesh`` when the mesh spans
    processes (an all-gather across them, so every process can ``local_copy`` the result); else
    ``tree`` unchanged."""
    if not spans_processes(mesh):
        return tree
    return jax.lax.with_sharding_constraint(tree, NamedSharding(mesh, PartitionSpec()))


def local_copy(tree: Any) -> Any:
    """This process's copy of replicated arrays (a single-device array each)."""
    return jax.tree.map(lambda x: x.addressable_data(0), tree)


def batch_sharding(mesh: Mesh | None = None) -> NamedSharding:
    """Leading axis split over the mesh."""
    return NamedSharding(batch_mesh() if mesh is None else mesh, PartitionSpec(AXIS))


def sharded_batch(fn, args: tuple, axes: tuple, mesh: Mesh | None = None) -> Any:
    """``fn(*args)`` with the leading axis of every ``args[i]`` whose ``axes[i]`` is 0 split over
    the mesh (entries with axis None are replicated). ``fn`` must map a batch to outputs with
    the same leading batch axis, entry by entry. Traceable (use inside ``jit``)."""
    mesh = batch_mesh() if mesh is None else mesh
    n_dev = mesh.size
    batched = [a for a, ax in zip(args, axes, strict=True) if ax is not None]
    size = jax.tree_util.tree_leaves(batched)[0].shape[0]
    pad = -size % n_dev

    def padded(x):
        x = jnp.asarray(x)
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    def deal(x):  # entry i -> block (i mod n_dev), position i // n_dev
        x = padded(x)
        return jnp.swapaxes(x.reshape((-1, n_dev) + x.shape[1:]), 0, 1).reshape(x.shape)

    def undeal(y):
        y = jnp.swapaxes(y.reshape((n_dev, -1) + y.shape[1:]), 0, 1).reshape(y.shape)
        return y[:size]

    if n_dev > 1:
        args = tuple(jax.tree.map(deal, a) if ax is not None else a for a, ax in zip(args, axes, strict=True))
    specs = tuple(PartitionSpec(AXIS) if ax is not None else PartitionSpec() for ax in axes)
    out = jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(AXIS), check_vma=False)(*args)
    return jax.tree.map(undeal, out) if n_dev > 1 else out
