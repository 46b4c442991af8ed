"""A learned residual on top of adaptive backstepping (issue 38): told the delay D only, like the adaptive law.

    h = h_adaptive(x; alpha_hat, D) + h_bar (-eta2(D, alpha_hat) S v~ / v_bar + eta3(D, alpha_hat) S rho~ / rho_bar)

h_adaptive is ``control.adaptive`` (backstepping whose model's alpha is estimated online; its estimator state is
this controller's state), the correction is the filtered gain law of ``control.gain_law`` without its eta1
term (the output's own feedback would move the adaptive law's equilibrium time gap h*), with the deviations
from the nominal equilibrium (the target the adaptive law holds) filtered by S (Gaussian, ``filter_sigma``).
The two gains are a bilinear interpolation of a table (Kd, Ka, 2) over knots in the told delay D (s) and in the
current estimate alpha_hat, held beyond the end knots. A zero table is the adaptive law: the correction is
exactly 0 (h_bar * 0), and the closed loops agree to float rounding (XLA compiles the two programs with
different fusions: 1 ulp of density after 200 steps on a 41-point grid; same map counts, tests and
benchmarks/adaptive_residual.py).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control.adaptive import AdaptiveSettings, EstimatorState, adaptive_backstepping
from jaxtraffic.control.adaptive import _act as _adaptive_act
from jaxtraffic.control.adaptive import _init as _adaptive_init
from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_law import FILTER_SIGMA, sigma_nodes
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.model.spatial import smooth
from jaxtraffic.platform.tracing import is_traced

Array = jax.Array
DELAY_KNOTS = (0.0, 4.0, 8.0)  # s: the default knots of the table in the told delay
ALPHA_KNOTS = (0.05, 0.3, 0.6)  # the default knots in the estimate alpha_hat (the map's range)


@struct.dataclass
class ResidualSettings:
    """Settings of ``adaptive_residual``: the adaptive law's (``adaptive``, its own ``delay`` field unused),
    the told delay (s), the knots in D (Kd,) s and in alpha_hat (Ka,), the gain table (Kd, Ka, 2) of
    [eta2, eta3] (dimensionless)."""

    adaptive: AdaptiveSettings
    delay: Array
    delay_knots: Array
    alpha_knots: Array
    table: Array


def interp2(x: Array, y: Array, xs: Array, ys: Array, table: Array) -> Array:
    """Bilinear interpolation of ``table`` (Kx, Ky, ...) at (x, y), clamped to the knots (held beyond them)."""
    def weights(z, zs):
        n = zs.shape[0]
        if n == 1:
            return jnp.ones((1,), table.dtype)
        z = jnp.clip(z, zs[0], zs[-1])
        i = jnp.clip(jnp.searchsorted(zs, z, side="right") - 1, 0, n - 2)
        t = (z - zs[i]) / (zs[i + 1] - zs[i])
        return jnp.zeros((n,), table.dtype).at[i].add(1.0 - t).at[i + 1].add(t)

    wx, wy = weights(x, xs), weights(y, ys)
    return jnp.einsum("i,j,ij...->...", wx, wy, table)


def residual_gains(settings: ResidualSettings, alpha_hat: Array) -> Array:
    """[eta2, eta3] at the told delay and the estimate ``alpha_hat``."""
    return interp2(settings.delay, alpha_hat, settings.delay_knots, settings.alpha_knots, settings.table)


@functools.cache
def _residual_act(sigma: float):
    def act(settings: ResidualSettings, cs: EstimatorState, obs, nominal: TrafficParams, key):
        h_ad, cs = _adaptive_act(settings.adaptive.replace(delay=settings.delay), cs, obs, nominal, key)
        rho_bar, v_bar = equilibrium(nominal)
        rho_t, v_t = obs.rho - rho_bar, obs.v - v_bar
        if sigma:
            rho_t, v_t = smooth(rho_t, sigma), smooth(v_t, sigma)
        g = residual_gains(settings, cs.alpha_hat)
        return h_ad + nominal.h_bar * (-g[0] * v_t / v_bar + g[1] * rho_t / rho_bar), cs

    return act


def _init(settings: ResidualSettings, obs, nominal: TrafficParams) -> EstimatorState:
    return _adaptive_init(settings.adaptive, obs, nominal)


def adaptive_residual(table: Array | None = None, delay: float | Array = 4.0, *,
                      delay_knots=DELAY_KNOTS, alpha_knots=ALPHA_KNOTS, filter_sigma: float = FILTER_SIGMA,
                      dx: float = 5.0, **adaptive) -> Controller:
    """Adaptive backstepping (``adaptive_backstepping(**adaptive)``, default settings) plus the learned
    correction of the module docstring. ``table``: (Kd, Ka, 2) gains [eta2, eta3] at ``delay_knots`` (s) x
    ``alpha_knots`` (default zeros: the adaptive law); ``delay``: the told delay (s; ``tell_delay`` sets it);
    ``filter_sigma`` (m, static) and ``dx`` (the controller grid's spacing, m) as in ``constant_gains``.
    Its state is the adaptive law's ``EstimatorState``."""
    dk, ak = jnp.asarray(delay_knots, jnp.float32), jnp.asarray(alpha_knots, jnp.float32)
    for name, k in (("delay_knots", delay_knots), ("alpha_knots", alpha_knots)):
        if not is_traced(k) and (np.ndim(k) != 1 or np.any(np.diff(np.asarray(k, float)) <= 0)):
            raise ValueError(f"{name} must be increasing (K,), got {np.asarray(k).tolist()}")
    shape = (dk.shape[0], ak.shape[0], 2)
    table = jnp.zeros(shape, jnp.float32) if table is None else jnp.asarray(table, jnp.float32)
    if table.shape != shape:
        raise ValueError(f"the residual's table must have shape {shape}, got {table.shape}")
    base = adaptive_backstepping(delay, **adaptive).settings
    settings = ResidualSettings(adaptive=base, delay=jnp.asarray(delay, jnp.float32), delay_knots=dk,
                                alpha_knots=ak, table=table)
    return Controller(settings=settings, act_fn=_residual_act(sigma_nodes(filter_sigma, dx)), init_fn=_init,
                      name=f"adaptive residual (sigma {filter_sigma:g} m)")
