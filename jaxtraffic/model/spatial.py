"""Spatial operators on nodal fields (pure, shape-static): transfer between grids and smoothing.

Nodes x_i = i dx, i = 0..n-1, cover [0, L] with both ends on nodes. A grid refined r times has
n_fine - 1 = r (n - 1); ``restrict`` and ``prolong`` move nodal values between the two (used by
``control.adapter``), ``smooth`` is the Gaussian filter of the gain law's observation
(``control.gain_law``), both renormalised where their kernel leaves the road.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array

KERNEL_HALF_WIDTH = 3.0  # the Gaussian kernel is cut at this many sigma


def restrict(u: Array, r: int) -> Array:
    """Full-weighting restriction of nodal values (shape (m r + 1,)) to every r-th node, shape
    (m + 1,): hat weights (r - |j|) / r^2, renormalised where the hat leaves the road. r = 1: ``u``."""
    if r == 1:
        return u
    w = (r - np.abs(np.arange(-r + 1, r))).astype(np.float64)
    mass = np.convolve(np.ones(u.shape[0]), w, mode="same")[::r]  # the hat's weight inside the road
    return jnp.convolve(u, jnp.asarray(w, u.dtype), mode="same")[::r] * jnp.asarray(1.0 / mass, u.dtype)


def prolong(u: Array, r: int) -> Array:
    """Linear interpolation of nodal values (shape (m + 1,)) to a grid refined r times, (m r + 1,)."""
    if r == 1:
        return u
    f = jnp.asarray(np.arange(r) / r, u.dtype)
    inner = u[:-1, None] * (1.0 - f) + u[1:, None] * f
    return jnp.concatenate([inner.reshape(-1), u[-1:]])


@functools.cache
def _gaussian_weights(sigma_nodes: float) -> np.ndarray:
    """Normalised-shape Gaussian weights exp(-j^2 / (2 s^2)), j = -J..J, J = ceil(3 s) (s in nodes)."""
    half = int(np.ceil(KERNEL_HALF_WIDTH * sigma_nodes))
    j = np.arange(-half, half + 1, dtype=np.float64)
    return np.exp(-0.5 * (j / sigma_nodes) ** 2)


def smooth(u: Array, sigma_nodes: float) -> Array:
    """Gaussian filter of nodal values ``u`` (shape (n,)), width ``sigma_nodes`` in node spacings
    (static; sigma / dx for a width sigma in m): sum_j w_j u_{i+j} / sum_j w_j over the nodes inside
    the road, w_j = exp(-j^2 / (2 sigma_nodes^2)), |j| <= 3 sigma_nodes. 0: ``u`` itself. A constant
    field is unchanged; in the interior a mode exp(i k x) is multiplied by about exp(-(k sigma)^2 / 2)."""
    if sigma_nodes == 0:
        return u
    if not sigma_nodes > 0:
        raise ValueError(f"filter width must be >= 0, got {sigma_nodes}")
    w = _gaussian_weights(float(sigma_nodes))
    n = u.shape[0]
    if w.size > n:  # a kernel wider than the road: "same" would return the kernel's length; the centred n
        half = (w.size - 1) // 2
        full = np.convolve(np.ones(n), w, mode="full")[half: half + n]
        return jnp.convolve(u, jnp.asarray(w, u.dtype), mode="full")[half: half + n] * jnp.asarray(1.0 / full,
                                                                                                   u.dtype)
    mass = np.convolve(np.ones(n), w, mode="same")
    return jnp.convolve(u, jnp.asarray(w, u.dtype), mode="same") * jnp.asarray(1.0 / mass, u.dtype)
