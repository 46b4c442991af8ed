"""Sensor noise on any control law (docs/model.md section 20): the law sees each node's density and speed with a
relative Gaussian error, drawn afresh at every control step and independently at every node (white in space and
time), rho (1 + level e1) and v (1 + level e2), e1, e2 ~ N(0, 1). ``level`` (dimensionless: 0.05 is a 5 % error) is
a traced setting, a scalar or one per environment of a batch (``batch_controller=True``), so that the scenarios of
a comparison can each have their own. A level of 0 gives the law's own values (to float rounding: the program is
compiled apart) for a deterministic law (a stochastic law then draws from another key)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.control.base import Controller
from jaxtraffic.platform.tracing import is_traced

__all__ = ["HeldNoise", "NoisySettings", "draw_factors", "held_noise", "measured", "sensor_noise"]


@struct.dataclass
class NoisySettings:
    """The law's own ``inner`` settings and the relative error ``level`` of its measurements (dimensionless)."""

    inner: Any
    level: jax.Array


@struct.dataclass
class HeldNoise:
    """The law's own ``inner`` settings and the factors (1 + level e) of this step's measurement, shape (2, n)."""

    inner: Any
    factors: jax.Array


def draw_factors(key: jax.Array, level: jax.Array | float, shape: tuple, dtype: Any) -> jax.Array:
    """One measurement's error as factors 1 + level e of density and speed, e ~ N(0, 1), shape (2,) + ``shape``."""
    return 1.0 + level * jax.random.normal(key, (2,) + tuple(shape), dtype)


def measured(obs, factors: jax.Array):
    """The observation ``obs`` as the sensors report it: rho and v times ``factors`` (``draw_factors``)."""
    return obs.replace(rho=obs.rho * factors[0], v=obs.v * factors[1])


def _noisy(obs, level, key):
    return measured(obs, draw_factors(key, level, obs.rho.shape, obs.rho.dtype))


@functools.cache
def _wrapped(act_fn: Callable, init_fn: Callable) -> tuple[Callable, Callable]:
    """(act_fn, init_fn) of a law seeing noisy measurements (cached: one function per law, so that equal noisy laws
    compile once)."""
    def act(settings: NoisySettings, cstate, obs, nominal, key):
        k_noise, k_law = jax.random.split(key)
        return act_fn(settings.inner, cstate, _noisy(obs, settings.level, k_noise), nominal, k_law)

    def init(settings: NoisySettings, obs, nominal):
        return init_fn(settings.inner, obs, nominal)

    return act, init


@functools.cache
def _held(act_fn: Callable, init_fn: Callable) -> tuple[Callable, Callable]:
    def act(settings: HeldNoise, cstate, obs, nominal, key):
        return act_fn(settings.inner, cstate, measured(obs, settings.factors), nominal, key)

    def init(settings: HeldNoise, obs, nominal):
        return init_fn(settings.inner, obs, nominal)

    return act, init


def held_noise(controller: Controller, factors: jax.Array) -> Controller:
    """``controller`` seeing its measurements through given ``factors`` (``draw_factors``, drawn by the caller):
    the gain environment holds one draw per step, so that the policy's features and its law see the same one, as
    ``sensor_noise`` has a deployed policy see them."""
    act, init = _held(controller.act_fn, controller.init_fn)
    return Controller(settings=HeldNoise(inner=controller.settings, factors=factors), act_fn=act, init_fn=init,
                      name=f"{controller.name} (sensor noise)")


def sensor_noise(controller: Controller, level: float | jax.Array, batched: bool = False) -> Controller:
    """``controller`` seeing its measurements with a relative error of standard deviation ``level`` (module
    docstring; >= 0, finite: checked when concrete). A (B,) ``level`` gives a batch of B controllers, run with
    ``batch_controller=True``: the law's settings are broadcast to a leading axis of B, unless ``batched`` says they
    have it already (a law given a batch of delays by ``tell_delay``, which must come first)."""
    level = jnp.asarray(level, jnp.float32)
    chex.assert_rank(level, {0, 1})
    if not is_traced(level) and not bool(jnp.all(jnp.isfinite(level) & (level >= 0))):  # (traced: the caller's)
        raise ValueError(f"sensor noise level must be finite and >= 0, got {level}")
    inner = controller.settings
    if level.ndim == 1 and not batched:
        inner = jax.tree.map(lambda x: jnp.broadcast_to(x, level.shape + jnp.shape(x)), inner)
    act, init = _wrapped(controller.act_fn, controller.init_fn)
    return Controller(settings=NoisySettings(inner=inner, level=level), act_fn=act, init_fn=init,
                      name=f"{controller.name} (sensor noise)")
