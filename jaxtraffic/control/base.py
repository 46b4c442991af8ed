"""The controller interface: ``Observation``, ``Controller`` and the actuator bound ``saturate``.

Every controller is a ``Controller`` pytree: its ``settings`` (gains, assumed delay, network
weights, ...) are traced leaves, so a batch of controller settings is a ``vmap`` over a batched
``Controller`` and changing a gain or an assumed delay never recompiles; the functions are static.

Interface (shared by the baselines, the gain law and the learned policy):
    cstate = controller.init(obs, nominal)
    h, cstate = controller.act(cstate, obs, nominal, key)
``obs`` is an ``Observation``; ``nominal`` is the ``TrafficParams`` the controller believes in
(its model: nominal alpha, the equilibrium target); ``key`` is a PRNG key for stochastic
controllers. The closed loop (``sim.plant.closed_loop_step``) saturates every returned field to
[h_min, h_max] (``saturate``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.model import delay as delay_buffer
from jaxtraffic.model.params import TrafficParams

Array = jax.Array


@struct.dataclass
class Observation:
    """What a controller sees at t_n: rho (veh/m), v (m/s), the previously sent time gap
    h_prev (s), the time t (s) and the buffer of time gaps it has sent (s)."""

    rho: Array
    v: Array
    h_prev: Array
    t: Array
    sent: delay_buffer.DelayBuffer


@struct.dataclass
class Controller:
    """A controller: traced ``settings`` plus static ``act_fn`` / ``init_fn``.

    act_fn(settings, cstate, obs, nominal, key) -> (h, cstate)
    init_fn(settings, obs, nominal) -> cstate
    """

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> Controller: ...

    settings: Any
    act_fn: Callable = struct.field(pytree_node=False)
    init_fn: Callable = struct.field(pytree_node=False, default=lambda s, o, n: ())
    name: str = struct.field(pytree_node=False, default="controller")

    def init(self, obs: Observation, nominal: TrafficParams) -> Any:
        return self.init_fn(self.settings, obs, nominal)

    def act(self, cstate: Any, obs: Observation, nominal: TrafficParams, key: Array) -> tuple[Array, Any]:
        h, cstate = self.act_fn(self.settings, cstate, obs, nominal, key)
        chex.assert_equal_shape([h, obs.rho])
        return h, cstate


def saturate(h: Array, p: TrafficParams) -> Array:
    """Clip a time-gap field to the actuator bounds [h_min, h_max] (s); NaN becomes h_bar (a
    defined value: the closed loop also flags such a step, see ``sim.plant``), +-inf a bound."""
    return jnp.clip(jnp.where(jnp.isnan(h), p.h_bar, h), p.h_min, p.h_max)



def takes_delay(controller: Controller) -> bool:
    """Whether ``controller`` is told the input delay it compensates (its settings have a ``delay``
    field: backstepping, a delay schedule)."""
    return hasattr(controller.settings, "delay")


def tell_delay(controller: Controller, delay: float | Array) -> Controller:
    """``controller`` told the delay ``delay`` (s). A (B,) array of delays gives a batch of B controllers
    (every other setting broadcast to a leading axis of B; run them with ``batch_controller=True``).
    ``ValueError`` if the controller takes no delay (``takes_delay``)."""
    if not takes_delay(controller):
        raise ValueError(f"{controller.name or 'this controller'} is not told a delay (its settings have no "
                         "'delay' field)")
    delay = jnp.asarray(delay, jnp.result_type(controller.settings.delay))
    settings = controller.settings
    if delay.ndim == 1:
        settings = jax.tree.map(lambda x: jnp.broadcast_to(x, delay.shape + jnp.shape(x)), settings)
    elif delay.ndim != 0:
        raise ValueError(f"delay must be a scalar or a (B,) batch, got shape {delay.shape}")
    return controller.replace(settings=settings.replace(delay=delay))
