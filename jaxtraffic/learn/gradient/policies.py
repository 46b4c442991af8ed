"""The gradient trainer's policies as a table of small objects (``POLICIES``): each one's initial parameters,
controller, trainable mask, the gains it applies when told a delay, its summary fields and the methods that
train it. ``learn.gradient.objective`` and ``cem`` and ``runs.gradient`` look a policy up here, by name.

    gains     three constant gains [eta1, eta2, eta3]
    schedule  gains scheduled in the told delay (a table over ``schedule_knots``)
    residual  adaptive backstepping plus a gain-law correction [eta2, eta3] over (told delay, alpha_hat)
    network   the actor network PPO trains (its gains depend on the state)

Each policy's default settings are ``learn.gradient.config.POLICY_DEFAULTS``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import chex
import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.adaptive_residual import ALPHA_KNOTS, adaptive_residual, residual_gains
from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_law import DelaySchedule, constant_gains, schedule_gains, scheduled_gains, sigma_nodes
from jaxtraffic.control.gain_policy import feature_size, policy_controller
from jaxtraffic.control.networks import ActorCritic

if TYPE_CHECKING:
    from jaxtraffic.learn.gradient.config import GradientConfig

Array = jax.Array
OBS_SCALE = 0.1  # std assumed for the normalised field deviations of the observation (dimensionless)


@dataclass(frozen=True)
class Policy:
    """One policy: ``init(config, n_points, g0, key)`` its parameters (``g0``: the initial gains), ``controller(
    theta, config, n_points, dx, delay)`` on its own grid, ``mask(config, theta)`` 1 where trained (0: held),
    ``gains(theta, config, delay)`` the gains (3,) it applies when told ``delay`` (None: state-dependent),
    ``summary(theta, config)`` its summary.json fields, and the methods that may train it."""

    init: Callable[..., Any]
    controller: Callable[..., Controller]
    gains: Callable[..., Array | None]
    summary: Callable[..., dict[str, Any]]
    mask: Callable[..., Array | float] = lambda config, theta: 1.0
    methods: tuple[str, ...] = ("adam", "cem")


def obs_statistics(n_points: int) -> tuple[Array, Array]:
    """Fixed observation normalisation of a gradient-trained network on ``n_points`` nodes: mean 0, std
    ``OBS_SCALE`` for the 3 n field entries and 1/sqrt(3) (a uniform variable on [-1, 1]) for the 3 gains."""
    var = jnp.concatenate([jnp.full((3 * n_points,), OBS_SCALE**2), jnp.full((3,), 1.0 / 3.0)])
    return jnp.zeros_like(var), var


def _gains_controller(theta, config: GradientConfig, n_points: int, dx: float, delay) -> Controller:
    chex.assert_shape(theta, (3,))
    return constant_gains(theta[0], theta[1], theta[2], config.filter_sigma, dx)


def _schedule_gains(theta, config: GradientConfig, delay) -> Array:
    return schedule_gains(DelaySchedule(knots=jnp.asarray(config.schedule_knots, theta.dtype), table=theta,
                                        delay=jnp.asarray(delay, theta.dtype)))


def _residual_mask(config: GradientConfig, theta: Array) -> Array:
    """The residual's rows at alpha_hat knots below ``residual_alpha_floor`` are held at zero (the adaptive law);
    broadcasts against its table."""
    keep = jnp.asarray(ALPHA_KNOTS) >= config.residual_alpha_floor
    return keep.astype(jnp.result_type(theta))[None, :, None]


def _residual_gains(theta, config: GradientConfig, delay) -> Array:
    """The correction's [0, eta2, eta3] at the initial estimate (the nominal's alpha, ``ALPHA_KNOTS``' paper
    value 0.15)."""
    ctrl = adaptive_residual(theta, delay, delay_knots=config.schedule_knots, alpha_knots=ALPHA_KNOTS)
    g = residual_gains(ctrl.settings, jnp.asarray(0.15, theta.dtype))
    return jnp.concatenate([jnp.zeros((1,), theta.dtype), g])


def _network_init(config: GradientConfig, n_points: int, g0: Array, key: Array) -> Any:
    """A network whose output is (nearly) ``g0`` everywhere: final actor bias atanh(g0 / grad_gain_max)."""
    params = ActorCritic(hidden=tuple(config.hidden)).init(key, jnp.zeros((feature_size(n_points),)))
    actor = params["params"]["actor"]
    last = sorted(k for k in actor if k.startswith("Dense_"))[-1]
    bias = jnp.arctanh(g0 / config.grad_gain_max)
    return {"params": {**params["params"], "actor": {**actor, last: {**actor[last], "bias": bias}}}}


def _network_controller(theta, config: GradientConfig, n_points: int, dx: float, delay) -> Controller:
    mean, var = obs_statistics(n_points)
    return policy_controller(theta, mean, var, config.grad_gain_max, hidden=tuple(config.hidden),
                             gain_filter=config.gain_filter, sigma_nodes=sigma_nodes(config.filter_sigma, dx))


POLICIES: dict[str, Policy] = {
    "gains": Policy(
        init=lambda config, n, g0, key: g0, controller=_gains_controller,
        gains=lambda theta, config, delay: jnp.asarray(theta),
        summary=lambda theta, config: {"gains": np.asarray(theta).tolist()}),
    "schedule": Policy(
        init=lambda config, n, g0, key: jnp.tile(g0, (len(config.schedule_knots), 1)),
        controller=lambda theta, config, n, dx, delay: scheduled_gains(theta, config.schedule_knots, delay,
                                                                      config.filter_sigma, dx),
        gains=_schedule_gains,
        summary=lambda theta, config: {"schedule": {"knots_s": list(config.schedule_knots),
                                                    "gains": np.asarray(theta).tolist()}}),
    "residual": Policy(  # [eta2, eta3] at every (delay, alpha_hat) knot; zeros: the adaptive law
        init=lambda config, n, g0, key: jnp.tile(g0[1:], (len(config.schedule_knots), len(ALPHA_KNOTS), 1))
        * _residual_mask(config, g0),
        controller=lambda theta, config, n, dx, delay: adaptive_residual(
            theta, delay, delay_knots=config.schedule_knots, alpha_knots=ALPHA_KNOTS,
            filter_sigma=config.filter_sigma, dx=dx),
        gains=_residual_gains, mask=_residual_mask, methods=("cem",),  # its predictor: no reverse mode
        summary=lambda theta, config: {"residual": {"delay_knots_s": list(config.schedule_knots),
                                                    "alpha_knots": list(ALPHA_KNOTS),
                                                    "table": np.asarray(theta).tolist()}}),
    "network": Policy(init=_network_init, controller=_network_controller, gains=lambda theta, config, delay: None,
                      summary=lambda theta, config: {}, methods=("adam",)),
}
