"""Grid transfer and smoothing operators (model.spatial): exactness, adjointness, filter response."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic.model.spatial import prolong, restrict, smooth


@pytest.mark.parametrize("r", [2, 3, 4])
def test_prolong_is_exact_for_linear_fields(r):
    coarse = np.linspace(0.0, 1.0, 11)
    fine = np.asarray(prolong(jnp.asarray(2.0 + 3.0 * coarse), r))
    assert fine.shape == (10 * r + 1,)
    np.testing.assert_allclose(fine, 2.0 + 3.0 * np.linspace(0.0, 1.0, 10 * r + 1), rtol=1e-6)


@pytest.mark.parametrize("r", [2, 3, 4])
def test_restrict_keeps_constants_and_interior_linear_fields(r):
    x = np.linspace(0.0, 1.0, 10 * r + 1)
    np.testing.assert_allclose(restrict(jnp.full(x.shape, 0.7), r), 0.7, rtol=1e-6)
    out = np.asarray(restrict(jnp.asarray(1.0 + x), r))
    np.testing.assert_allclose(out[1:-1], 1.0 + np.linspace(0.0, 1.0, 11)[1:-1], rtol=1e-6)


@pytest.mark.parametrize("r", [2, 3])
def test_restrict_is_the_row_normalised_adjoint_of_prolong(r):
    m = 6
    P = np.stack([np.asarray(prolong(jnp.eye(m + 1)[i], r)) for i in range(m + 1)], axis=1)  # (fine, coarse)
    R = np.stack([np.asarray(restrict(jnp.eye(m * r + 1)[j], r)) for j in range(m * r + 1)], axis=1)
    expected = P.T / P.T.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(R, expected, atol=1e-7)


def test_identity_at_ratio_one_and_zero_width():
    u = jnp.asarray(np.random.default_rng(0).normal(size=17))
    assert restrict(u, 1) is u and prolong(u, 1) is u and smooth(u, 0.0) is u
    with pytest.raises(ValueError, match="filter width"):
        smooth(u, -1.0)


def test_smooth_keeps_constants_and_damps_a_mode_like_a_gaussian():
    n, sigma = 801, 8.0  # nodes
    np.testing.assert_allclose(smooth(jnp.full((n,), 3.0), sigma), 3.0, rtol=1e-6)
    for wavelength in (40.0, 100.0):
        k = 2 * np.pi / wavelength
        u = np.cos(k * np.arange(n))
        out = np.asarray(smooth(jnp.asarray(u), sigma))
        inner = slice(100, -100)
        gain = np.dot(out[inner], u[inner]) / np.dot(u[inner], u[inner])
        assert gain == pytest.approx(np.exp(-0.5 * (k * sigma) ** 2), abs=5e-3)  # the kernel is cut at 3 sigma


@pytest.mark.parametrize("sigma_nodes", [2.0, 5.0, 20.0])
def test_smooth_with_a_kernel_wider_than_the_road_is_the_normalised_sum(sigma_nodes):
    """A filter wider than a coarse road (25 m on a 50 m grid of 21 nodes is fine; 250 m is not) keeps the
    road's length and is the normalised Gaussian sum over the nodes inside it (the oracle, in float64)."""
    u = np.random.default_rng(0).normal(size=21)
    got = np.asarray(smooth(jnp.asarray(u, jnp.float32), sigma_nodes))
    half = int(np.ceil(3 * sigma_nodes))
    j = np.arange(21)
    w = np.exp(-0.5 * ((j[None, :] - j[:, None]) / sigma_nodes) ** 2) * (np.abs(j[None, :] - j[:, None]) <= half)
    np.testing.assert_allclose(got, (w @ u) / w.sum(axis=1), atol=2e-6)


@pytest.mark.parametrize("sigma_nodes", [0.7, 2.5, 5.0, 12.0])
def test_smooth_is_the_normalised_convolution_to_float32_rounding(sigma_nodes):
    """The shifted multiply-adds compute the convolution with the Gaussian weights inside the road (float64 oracle)."""
    from jaxtraffic.model.spatial import _gaussian_weights

    u = np.random.default_rng(0).normal(size=101).astype(np.float32)
    w = _gaussian_weights(sigma_nodes)
    oracle = np.convolve(u.astype(np.float64), w, mode="same") / np.convolve(np.ones(101), w, mode="same")
    np.testing.assert_allclose(np.asarray(smooth(jnp.asarray(u), sigma_nodes)), oracle, rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("r", [2, 4])
def test_restrict_is_the_normalised_hat_sum_to_float32_rounding(r):
    u = np.random.default_rng(1).normal(size=20 * r + 1).astype(np.float32)
    w = (r - np.abs(np.arange(-r + 1, r))).astype(np.float64)
    oracle = (np.convolve(u.astype(np.float64), w, mode="same") / np.convolve(np.ones(u.size), w, mode="same"))[::r]
    np.testing.assert_allclose(np.asarray(restrict(jnp.asarray(u), r)), oracle, rtol=2e-6, atol=2e-6)
