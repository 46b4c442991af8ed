"""The paper's three-gain law (docs/controllers.md; docs/model.md section 9) and constant gains.

    h = h_bar + h_bar (-eta1 h~_prev/h_bar - eta2 S v~/v_bar + eta3 S rho~/rho_bar)   (tildes: deviations)

S is the identity (the paper's pointwise law) or a Gaussian filter of width sigma (m) over x
(``model.spatial.smooth``): the law's own spatial scale, which keeps the delayed loop stable at
the high wavenumbers a pointwise law destabilises (``control.stability``, docs/model.md section 16).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control.base import Controller, Observation
from jaxtraffic.model.linear import linearize
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.model.spatial import smooth
from jaxtraffic.platform.tracing import is_traced

Array = jax.Array

GAIN_NAMES = ("eta1", "eta2", "eta3")
# m, the default width of the learned gain law's spatial filter (``learn``): of 0, 10, 15, 20, 25, 30 m, the
# smallest at which both the gradient-trained gains and the default PPO policy are certified with a margin
# (max growth <= 2e-4/s; at 20 m the gains sit at the tolerance and PPO above it; docs/model.md section 16,
# "Used in training")
FILTER_SIGMA = 25.0


def gain_law(gains: Array, obs: Observation, nominal: TrafficParams,
             eq: tuple[Array, Array] | None = None, sigma_nodes: float = 0.0) -> Array:
    """The paper's three-gain law on normalised deviations (docs/model.md section 9).

    h = h_bar + h_bar * (-eta1 (h_prev - h_bar)/h_bar - eta2 S(v - v_bar)/v_bar
                         + eta3 S(rho - rho_bar)/rho_bar),
    with dimensionless gains ``gains = [eta1, eta2, eta3]`` (shape (3,)); ``eq``: (rho_bar, v_bar)
    of ``nominal`` if the caller has it already (default: computed); S: the Gaussian filter of
    width ``sigma_nodes`` node spacings (static; 0: none, the paper's pointwise law).
    """
    chex.assert_shape(gains, (3,))
    rho_bar, v_bar = equilibrium(nominal) if eq is None else eq
    h_bar = nominal.h_bar
    rho_t, v_t = obs.rho - rho_bar, obs.v - v_bar
    if sigma_nodes:
        rho_t, v_t = smooth(rho_t, sigma_nodes), smooth(v_t, sigma_nodes)
    dev = -gains[0] * (obs.h_prev - h_bar) / h_bar - gains[1] * v_t / v_bar + gains[2] * rho_t / rho_bar
    return h_bar + h_bar * dev


def lyapunov_equivalent_gains(k: float | Array, nominal: TrafficParams) -> Array:
    """Gains [eta1, eta2, eta3] for which ``gain_law`` is the Lyapunov law with gain ``k``.

    Matching h_bar (-eta2 v~/v_bar + eta3 rho~/rho_bar) = ((1 - k) v~ - V_rho rho~)/V_h gives
    eta1 = 0, eta2 = (k - 1) v_bar / (h_bar V_h), eta3 = -V_rho rho_bar / (h_bar V_h)
    (all dimensionless). At the paper's defaults: eta2 = -1.283333 (k - 1), eta3 = -2.770561, so the
    Lyapunov law is *not* inside the paper's sigmoid range (0, 1) of gains (docs/model.md sections 7 and 9).
    """
    lm = linearize(nominal)
    k = jnp.asarray(k, lm.V_h.dtype)
    scale = lm.h_bar * lm.V_h
    return jnp.stack([jnp.zeros_like(k), (k - 1.0) * lm.v_bar / scale,
                      jnp.broadcast_to(-lm.V_rho * lm.rho_bar / scale, jnp.shape(k))], axis=-1)


def _gain_act(settings, cstate, obs, nominal, key):
    return gain_law(settings, obs, nominal), cstate


@functools.cache
def _filtered_gain_act(sigma_nodes: float):
    def act(settings, cstate, obs, nominal, key):
        return gain_law(settings, obs, nominal, sigma_nodes=sigma_nodes), cstate

    return act


def constant_gains(eta1: float = 0.0, eta2: float = 0.0, eta3: float = 0.0, filter_sigma: float = 0.0,
                   dx: float = 5.0) -> Controller:
    """The three-gain law with constant gains (what a PPO policy outputs, frozen); ``filter_sigma``
    (m, static): width of the Gaussian filter of the observed rho~, v~ on the controller's grid of
    spacing ``dx`` (m; the paper's 5 m by default), 0: the pointwise law."""
    settings = jnp.asarray([eta1, eta2, eta3], float)
    if filter_sigma:
        return Controller(settings=settings, act_fn=_filtered_gain_act(sigma_nodes(filter_sigma, dx)),
                          name=f"constant_gains (sigma {filter_sigma:g} m)")
    return Controller(settings=settings, act_fn=_gain_act, name="constant_gains")


def sigma_nodes(filter_sigma: float, dx: float) -> float:
    """A filter width in m as node spacings of a grid of spacing ``dx`` (m); ``ValueError`` if negative."""
    if not (np.isfinite(filter_sigma) and filter_sigma >= 0):
        raise ValueError(f"filter_sigma must be a finite width >= 0 m, got {filter_sigma}")
    return float(filter_sigma) / float(dx)



@struct.dataclass
class DelaySchedule:
    """Settings of ``scheduled_gains``: a family of gain triples scheduled in the input delay.

    knots: (K,) increasing delays, s; table: (K, 3) gains [eta1, eta2, eta3] at the knots (dimensionless);
    delay: the delay the controller is told it must compensate, s (as backstepping is; not the plant's
    alpha). The gains used are the table interpolated linearly at ``delay``, held beyond the end knots.
    """

    knots: Array
    table: Array
    delay: Array


def schedule_gains(s: DelaySchedule) -> Array:
    """The gains (3,) of the schedule ``s`` at its told delay."""
    chex.assert_rank([s.knots, s.table, s.delay], [1, 2, 0])
    return jax.vmap(lambda column: jnp.interp(s.delay, s.knots, column), in_axes=1)(s.table)


def scheduled_gains(table: Array, knots: Array | Sequence[float], delay: float | Array = 4.0,
                    filter_sigma: float = FILTER_SIGMA, dx: float = 5.0) -> Controller:
    """The three-gain law with gains scheduled in the told delay (``DelaySchedule``): ``table`` (K, 3) at the
    ``knots`` (K,) s; ``filter_sigma`` (m, static) and ``dx`` (m) as in ``constant_gains``. ``tell_delay``
    (``control.base``) sets the delay, or a batch of delays."""
    if not is_traced(knots) and np.any(np.diff(np.asarray(knots, float)) <= 0):
        raise ValueError(f"the schedule's knots must increase, got {np.asarray(knots).tolist()}")
    knots = jnp.asarray(knots, float)
    table = jnp.asarray(table, float)
    if knots.ndim != 1 or table.shape != (knots.shape[0], 3) or knots.shape[0] < 1:
        raise ValueError(f"a delay schedule needs knots (K,) and a table (K, 3), got {knots.shape} and {table.shape}")
    settings = DelaySchedule(knots=knots, table=table, delay=jnp.asarray(delay, float))
    return Controller(settings=settings, act_fn=_scheduled_act(sigma_nodes(filter_sigma, dx)),
                      name=f"delay-scheduled gains (sigma {filter_sigma:g} m)")


@functools.cache
def _scheduled_act(sigma_nodes: float):
    def act(settings, cstate, obs, nominal, key):
        return gain_law(schedule_gains(settings), obs, nominal, sigma_nodes=sigma_nodes), cstate

    return act
