"""Controllers: pure functions from an observation to the ACC time-gap field.

Every controller is a ``Controller`` pytree: its ``settings`` (gains, assumed delay, network
weights, ...) are traced leaves, so a batch of controller settings is a ``vmap`` over a batched
``Controller`` and changing a gain or an assumed delay never recompiles; the functions are static.

Interface (shared by the baselines and the PPO policy):
    cstate = controller.init(obs, nominal)
    h, cstate = controller.act(cstate, obs, nominal, key)
``obs`` is an ``Observation``; ``nominal`` is the ``TrafficParams`` the controller believes in
(its model: nominal alpha, the equilibrium target); ``key`` is a PRNG key for stochastic
controllers. The rollout saturates every returned field to [h_min, h_max] (``saturate``).

Laws (MODEL.md sections 7-9; see docs/controllers.md for sources and differences):
    open_loop:     h = h_bar
    gain_law:      h = h_bar + h_bar (-eta1 h~_prev/h_bar - eta2 v~/v_bar + eta3 rho~/rho_bar)
    lyapunov:      U = ((1 - k) v~ - V_rho rho~) / V_h
    backstepping:  the Lyapunov law applied to the state predicted D_ctrl ahead
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import chex
import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic import delay as delay_buffer
from jaxtraffic import fundamental as fd
from jaxtraffic.linear import LinearModel, linear_step, linearize, riemann_w
from jaxtraffic.params import TrafficParams, equilibrium

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
    """Clip a time-gap field to the actuator bounds [h_min, h_max] (s)."""
    return jnp.clip(h, p.h_min, p.h_max)


# ----------------------------------------------------------------------------- open loop
def _open_loop_act(settings, cstate, obs, nominal, key):
    return jnp.full_like(obs.rho, nominal.h_bar), cstate


def open_loop() -> Controller:
    """The uncontrolled system: h = h_bar everywhere."""
    return Controller(settings=(), act_fn=_open_loop_act, name="open_loop")


# ----------------------------------------------------------------------------- gain law
GAIN_NAMES = ("eta1", "eta2", "eta3")


def gain_law(gains: Array, obs: Observation, nominal: TrafficParams) -> Array:
    """The paper's three-gain law on normalised deviations (MODEL.md section 9).

    h = h_bar + h_bar * (-eta1 (h_prev - h_bar)/h_bar - eta2 (v - v_bar)/v_bar
                         + eta3 (rho - rho_bar)/rho_bar),
    with dimensionless gains ``gains = [eta1, eta2, eta3]`` (shape (3,)).
    """
    chex.assert_shape(gains, (3,))
    rho_bar, v_bar = equilibrium(nominal)
    h_bar = nominal.h_bar
    dev = (-gains[0] * (obs.h_prev - h_bar) / h_bar - gains[1] * (obs.v - v_bar) / v_bar
           + gains[2] * (obs.rho - rho_bar) / rho_bar)
    return h_bar + h_bar * dev


def _gain_act(settings, cstate, obs, nominal, key):
    return gain_law(settings, obs, nominal), cstate


def constant_gains(eta1: float = 0.0, eta2: float = 0.0, eta3: float = 0.0) -> Controller:
    """The three-gain law with constant gains (what a PPO policy outputs, frozen)."""
    return Controller(settings=jnp.asarray([eta1, eta2, eta3], float), act_fn=_gain_act,
                      name="constant_gains")


# ----------------------------------------------------------------------------- Lyapunov
@struct.dataclass
class LyapunovSettings:
    k: Array  # decay gain of v~, dimensionless (> 0)


def lyapunov_law(rho: Array, v: Array, k: Array, lm: LinearModel) -> Array:
    """U = (w - k v~)/V_h = ((1 - k) v~ - V_rho rho~)/V_h; returns h = h_bar + U (s)."""
    rho_t, v_t = rho - lm.rho_bar, v - lm.v_bar
    return lm.h_bar + (riemann_w(rho_t, v_t, lm) - k * v_t) / lm.V_h


def _lyapunov_act(settings, cstate, obs, nominal, key):
    return lyapunov_law(obs.rho, obs.v, settings.k, linearize(nominal)), cstate


def _lyapunov_nonlinear_act(settings, cstate, obs, nominal, key):
    _, v_bar = equilibrium(nominal)
    v_target = obs.v - settings.k * (obs.v - v_bar)
    # speed matching: V(rho, h) = v_target, i.e. h_mix(h) = (1/rho - l)/v_target
    hm = (1.0 / obs.rho - nominal.l) / jnp.maximum(v_target, 1e-6)
    c = nominal.alpha + (1.0 - nominal.alpha) * nominal.tau_acc / nominal.tau_m
    b = (1.0 - nominal.alpha) * nominal.tau_acc / nominal.tau_m / nominal.h_m
    hm = jnp.minimum(hm, 0.999 * c / b)  # h_mix saturates at c/b: beyond it no h exists
    return fd.h_mix_inv(hm, nominal), cstate


def lyapunov(k: float | Array = 1.0, nonlinear: bool = False) -> Controller:
    """Lyapunov in-domain feedback (MODEL.md section 7), gain ``k`` > 0.

    ``nonlinear=True`` uses the speed-matching variant h = h_mix^{-1}((1/rho - l)/(v - k v~)).
    """
    act = _lyapunov_nonlinear_act if nonlinear else _lyapunov_act
    return Controller(settings=LyapunovSettings(k=jnp.asarray(k, float)), act_fn=act,
                      name="lyapunov_nl" if nonlinear else "lyapunov")


# ----------------------------------------------------------------------------- predictor
@struct.dataclass
class BacksteppingSettings:
    k: Array  # Lyapunov gain of the target law, dimensionless
    delay: Array  # assumed input delay D_ctrl, s (may differ from the plant's)


def predict(rho_t: Array, v_t: Array, sent: delay_buffer.DelayBuffer, d: Array,
            lm: LinearModel) -> tuple[Array, Array]:
    """Deviation state predicted ``d`` steps ahead by the discrete linear model.

    Step j (j = 0..d-1) applies the input sent d - j steps before now, i.e. ``read(sent, d-1-j)``,
    which is what the plant will apply if its delay is d. Costs d cheap linear steps.
    """
    def body(j, carry):
        r, v = carry
        U = delay_buffer.read(sent, d - 1 - j) - lm.h_bar
        return linear_step(r, v, U, lm)

    return jax.lax.fori_loop(0, d, body, (rho_t, v_t))


def _backstepping_act(settings, cstate, obs, nominal, key):
    lm = linearize(nominal)
    d = jnp.round(settings.delay / nominal.dt).astype(jnp.int32)
    d = jnp.clip(d, 0, obs.sent.size - 1)
    r_hat, v_hat = predict(obs.rho - lm.rho_bar, obs.v - lm.v_bar, obs.sent, d, lm)
    return lyapunov_law(r_hat + lm.rho_bar, v_hat + lm.v_bar, settings.k, lm), cstate


def backstepping(delay: float | Array = 4.0, k: float | Array = 1.0) -> Controller:
    """Delay-compensated (predictor / backstepping) feedback, MODEL.md section 8.

    Applies the Lyapunov law with gain ``k`` to the state predicted ``delay`` seconds ahead
    (its own assumed delay, independent of the plant's) by the linearised model with nominal
    parameters over the inputs already sent. With delay = 0 it equals ``lyapunov(k)``.
    """
    settings = BacksteppingSettings(k=jnp.asarray(k, float), delay=jnp.asarray(delay, float))
    return Controller(settings=settings, act_fn=_backstepping_act, name="backstepping")
