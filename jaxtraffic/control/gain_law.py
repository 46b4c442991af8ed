"""The paper's three-gain law (docs/controllers.md; docs/model.md section 9) and constant gains.

    h = h_bar + h_bar (-eta1 h~_prev/h_bar - eta2 v~/v_bar + eta3 rho~/rho_bar)   (tildes: deviations)
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from jaxtraffic.control.base import Controller, Observation
from jaxtraffic.model.linear import linearize
from jaxtraffic.model.params import TrafficParams, equilibrium

Array = jax.Array

GAIN_NAMES = ("eta1", "eta2", "eta3")


def gain_law(gains: Array, obs: Observation, nominal: TrafficParams,
             eq: tuple[Array, Array] | None = None) -> Array:
    """The paper's three-gain law on normalised deviations (docs/model.md section 9).

    h = h_bar + h_bar * (-eta1 (h_prev - h_bar)/h_bar - eta2 (v - v_bar)/v_bar
                         + eta3 (rho - rho_bar)/rho_bar),
    with dimensionless gains ``gains = [eta1, eta2, eta3]`` (shape (3,)); ``eq``: (rho_bar, v_bar)
    of ``nominal`` if the caller has it already (default: computed).
    """
    chex.assert_shape(gains, (3,))
    rho_bar, v_bar = equilibrium(nominal) if eq is None else eq
    h_bar = nominal.h_bar
    dev = (-gains[0] * (obs.h_prev - h_bar) / h_bar - gains[1] * (obs.v - v_bar) / v_bar
           + gains[2] * (obs.rho - rho_bar) / rho_bar)
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


def constant_gains(eta1: float = 0.0, eta2: float = 0.0, eta3: float = 0.0) -> Controller:
    """The three-gain law with constant gains (what a PPO policy outputs, frozen)."""
    return Controller(settings=jnp.asarray([eta1, eta2, eta3], float), act_fn=_gain_act,
                      name="constant_gains")

