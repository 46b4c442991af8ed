"""Batching helpers of the rollouts: batched parameters (``stack_params``) and a vmap computed in
sequential chunks (``chunked_vmap``)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.model.params import TrafficParams

__all__ = ["chunked_vmap", "stack_params"]


def chunked_vmap(fn, args: tuple, axes: tuple, chunk_size: int) -> Any:
    """``jax.vmap(fn, in_axes=axes)(*args)`` computed as a sequential ``lax.map`` over chunks of at
    most ``chunk_size`` batch entries (``axes`` entries are 0 or None; outputs get a leading batch
    axis).

    The batch is cut into n = ceil(size / chunk_size) chunks of ceil(size / n) consecutive
    entries (so at most n - 1 padded entries, copies of the last one, whose results are dropped).
    Consecutive entries: a batch ordered by cost (e.g. the assumed delay of a predictor, whose
    loop under ``vmap`` runs as long as the chunk's largest delay) keeps similar entries together.
    ``chunk_size`` <= 0 or >= the batch: a plain vmap.
    """
    idx = [i for i, ax in enumerate(axes) if ax is not None]
    batched = [args[i] for i in idx]
    size = jax.tree_util.tree_leaves(batched)[0].shape[0]
    if chunk_size <= 0 or size <= chunk_size:
        return jax.vmap(fn, in_axes=axes)(*args)
    n_chunks = -(-size // chunk_size)
    chunk = -(-size // n_chunks)
    pad = n_chunks * chunk - size

    def split(x):
        if pad:
            x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n_chunks, chunk) + x.shape[1:])

    def run_chunk(part):
        full = list(args)
        for i, a in zip(idx, part, strict=True):
            full[i] = a
        return jax.vmap(fn, in_axes=axes)(*full)

    out = jax.lax.map(run_chunk, jax.tree.map(split, batched))
    return jax.tree.map(lambda y: y.reshape((n_chunks * chunk,) + y.shape[2:])[:size], out)


_STATIC_FIELDS = ("n_points", "max_delay_steps", "scheme", "model")


def stack_params(*envs: TrafficParams, **fields: Any) -> TrafficParams:
    """A batched ``TrafficParams``, from concrete per-environment ones (``stack_params(*envs)``) or
    from keywords: each keyword is a sequence of per-environment values (or a scalar, shared by
    every environment); the others keep their defaults. Static fields are passed as scalars (and
    must agree between ``envs``). At least one keyword must be a sequence.

    Every environment is validated, then the float fields are stacked as float64 numpy arrays
    (leading batch axis), so that validation of the batch runs in double precision (in float32,
    7.0 / 0.1 misses the "multiple of dt" tolerance and delays >= 7 s would be wrongly rejected);
    inside ``jit`` they become float32 like any other input.
    """
    if envs and fields:
        raise ValueError("stack_params: give environments or keywords, not both")
    if not envs:
        static = {k: fields.pop(k) for k in _STATIC_FIELDS if k in fields}
        arrays = {k: np.asarray(v, np.float64) for k, v in fields.items()}
        sizes = {a.shape[0] for a in arrays.values() if a.ndim == 1}
        if any(a.ndim > 1 for a in arrays.values()):
            raise ValueError("stack_params: each field must be a scalar or a 1-d sequence")
        lengths = {k: a.shape[0] for k, a in arrays.items() if a.ndim == 1}
        if len(sizes) > 1:
            raise ValueError(f"stack_params: the batched fields have different lengths {lengths}; give each the "
                             "same number of environments (or a scalar, shared by all)")
        if not sizes:
            raise ValueError("stack_params: give at least one field as a sequence of per-environment values "
                             "(e.g. stack_params(delay=[0.0, 4.0])), or TrafficParams objects")
        (b,) = sizes
        if b == 0:
            raise ValueError(f"stack_params: the batched fields are empty ({lengths}); a batch needs at least one "
                             "environment")
        arrays = {k: np.broadcast_to(a, (b,)) for k, a in arrays.items()}
        base = TrafficParams(**static)
        envs = tuple(base.replace(**{k: np.asarray(a[i]).item() for k, a in arrays.items()}) for i in range(b))
    if not envs:
        raise ValueError("stack_params: give at least one environment (TrafficParams objects or keywords)")
    if len({tuple(getattr(e, f) for f in _STATIC_FIELDS) for e in envs}) != 1:
        raise ValueError(f"stack_params: the static fields {_STATIC_FIELDS} differ between environments")
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x, np.float64) for x in xs]), *envs)
