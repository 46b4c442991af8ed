"""Ring buffer of sent ACC time gaps implementing the input delay (docs/model.md section 4).

The capacity is static (``max_delay_steps``); the delay read from it is a traced integer, so one
compiled rollout serves a batch of different delays. Entry ``read(buf, k)`` is the input sent
``k`` steps ago (``k = 0``: the newest). Entries older than the buffer's history (``valid``
pushes since the last (re)start) read as ``fill`` (h_bar), so before t = D the plant receives
the nominal time gap. ``restart`` empties the history in O(n_points) without touching the
(capacity x n_points) data, which keeps environment resets cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import chex
import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class DelayBuffer:
    """Sent time gaps, s: ``data`` has shape (max_delay_steps + 1, n_points); ``head`` indexes
    the newest entry; ``valid`` counts the entries pushed since the (re)start (saturating at
    the size); ``fill`` (shape (n_points,)) is read for anything older."""

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> DelayBuffer: ...

    data: jax.Array
    head: jax.Array
    valid: jax.Array
    fill: jax.Array

    @property
    def size(self) -> int:
        return self.data.shape[0]


def init_buffer(h0: jax.Array, max_delay_steps: int) -> DelayBuffer:
    """A buffer of capacity ``max_delay_steps`` whose history reads as the field ``h0`` (shape (n,))."""
    chex.assert_rank(h0, 1)
    data = jnp.broadcast_to(h0, (max_delay_steps + 1, h0.shape[0]))
    zero = jnp.zeros((), jnp.int32)
    return DelayBuffer(data=jnp.array(data), head=zero, valid=zero, fill=h0)


def restart(buf: DelayBuffer, h0: jax.Array) -> DelayBuffer:
    """The same storage with an empty history that reads as ``h0``: O(n), data untouched."""
    chex.assert_equal_shape((h0, buf.fill))
    return buf.replace(valid=jnp.zeros((), jnp.int32), fill=h0.astype(buf.fill.dtype))


def push(buf: DelayBuffer, h: jax.Array) -> DelayBuffer:
    """Write the newly sent field ``h`` (shape (n,)) as the newest entry."""
    chex.assert_equal_shape((h, buf.data[0]))
    head = (buf.head + 1) % buf.size
    return buf.replace(data=buf.data.at[head].set(h.astype(buf.data.dtype)), head=head,
                       valid=jnp.minimum(buf.valid + 1, buf.size))


def read(buf: DelayBuffer, k: jax.Array | int) -> jax.Array:
    """The field sent ``k`` steps ago (0 <= k <= capacity; traced ``k`` allowed), or ``fill``
    if nothing was sent that long ago."""
    k = jnp.asarray(k, jnp.int32)
    idx = (buf.head - k) % buf.size
    row = jax.lax.dynamic_index_in_dim(buf.data, idx, axis=0, keepdims=False)
    return jnp.where(k < buf.valid, row, buf.fill)


def select_restarted(pred: jax.Array, restarted: DelayBuffer, buf: DelayBuffer) -> DelayBuffer:
    """``restarted`` where ``pred`` else ``buf``, for ``restarted = restart(buf, h0)``: the two share
    their storage, so only the O(n) bookkeeping is selected, never the (capacity x n) data."""
    return buf.replace(valid=jnp.where(pred, restarted.valid, buf.valid),
                       fill=jnp.where(pred, restarted.fill, buf.fill))
