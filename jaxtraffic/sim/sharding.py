"""Batches split over every local device: one code path for one device and many.

``sharded_batch(fn, args, axes)`` runs ``fn`` (a function of a batch) with its batch axis split
over a one-axis ``Mesh`` of this process's devices, ``jax.local_devices()`` (``shard_map``: each
device runs ``fn`` on its share; no communication). In a multi-process run
(``jaxtraffic.distributed``) each process simulates the whole batch on its own devices, so its
results are ordinary local arrays. Entries are dealt out like cards (entry i to device i mod
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

AXIS = "batch"

__all__ = ["AXIS", "batch_mesh", "batch_sharding", "sharded_batch"]


def batch_mesh(devices: list | None = None) -> Mesh:
    """A one-axis mesh (``AXIS``) over ``devices`` (default: this process's, ``jax.local_devices()``)."""
    return Mesh(np.array(jax.local_devices() if devices is None else devices), (AXIS,))


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
