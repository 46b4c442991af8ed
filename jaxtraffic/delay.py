"""Ring buffer of sent ACC time gaps implementing the input delay (MODEL.md section 4).

The capacity is static (``max_delay_steps``); the delay read from it is a traced integer, so one
compiled rollout serves a batch of different delays. Entry ``read(buf, k)`` is the input sent
``k`` steps ago (``k = 0``: the newest). The buffer starts filled with ``h_bar`` so that, before
t = D, the plant receives the nominal time gap.
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class DelayBuffer:
    """Sent time gaps, s: ``data`` has shape (max_delay_steps + 1, n_points); ``head`` indexes
    the newest entry."""

    data: jax.Array
    head: jax.Array

    @property
    def size(self) -> int:
        return self.data.shape[0]


def init_buffer(h0: jax.Array, max_delay_steps: int) -> DelayBuffer:
    """A buffer of capacity ``max_delay_steps`` filled with the field ``h0`` (shape (n,))."""
    chex.assert_rank(h0, 1)
    data = jnp.broadcast_to(h0, (max_delay_steps + 1, h0.shape[0]))
    return DelayBuffer(data=jnp.array(data), head=jnp.zeros((), jnp.int32))


def push(buf: DelayBuffer, h: jax.Array) -> DelayBuffer:
    """Write the newly sent field ``h`` (shape (n,)) as the newest entry."""
    chex.assert_equal_shape((h, buf.data[0]))
    head = (buf.head + 1) % buf.size
    return DelayBuffer(data=buf.data.at[head].set(h.astype(buf.data.dtype)), head=head)


def read(buf: DelayBuffer, k: jax.Array | int) -> jax.Array:
    """The field sent ``k`` steps ago (0 <= k <= capacity; traced ``k`` allowed)."""
    idx = (buf.head - jnp.asarray(k, jnp.int32)) % buf.size
    return jax.lax.dynamic_index_in_dim(buf.data, idx, axis=0, keepdims=False)
