"""Baseline controllers: open loop, Lyapunov and backstepping (predictor) feedback.

Each is a ``control.base.Controller`` (interface there).

Laws (docs/model.md sections 7-9; see docs/controllers.md for sources and differences):
    open_loop:     h = h_bar
    gain_law:      h = h_bar + h_bar (-eta1 h~_prev/h_bar - eta2 v~/v_bar + eta3 rho~/rho_bar)
    lyapunov:      h = h_bar + U,  U = ((1 - k) v~ - V_rho rho~) / V_h  (tildes: deviations)
    backstepping:  the Lyapunov law applied to the state predicted D_ctrl ahead by the
                   discrete linearised model (``predict``: D_ctrl/dt cheap linear steps)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control.base import Controller
from jaxtraffic.model import delay as delay_buffer
from jaxtraffic.model import fundamental as fd
from jaxtraffic.model.linear import LinearModel, linear_step, linearize, riemann_w
from jaxtraffic.model.params import TrafficParams, equilibrium
from jaxtraffic.platform.tracing import concrete, is_traced

Array = jax.Array


def _check_setting(name: str, value: float | Array, minimum: float | None = None) -> None:
    """Raise ``ValueError`` if a concrete controller setting is not a finite number (>= ``minimum``).
    Traced values (inside ``jit``/``vmap``) are not checked, and no ``jnp`` operation runs here: a
    controller can be built inside ``jax.jit`` (where even constants become tracers)."""
    if is_traced(value):
        return
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        x = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite, got {x.tolist()}")
    if minimum is not None and not np.all(x >= minimum):
        raise ValueError(f"{name} must be >= {minimum}, got {x.tolist()}")


def _check_share(keep: float | Array) -> None:
    """``ValueError`` unless a concrete ``keep`` (the share of w's damping kept) lies in [0, 1]."""
    _check_setting("keep (share of w's damping kept)", keep, minimum=0.0)
    if not is_traced(keep) and not np.all(np.asarray(keep, np.float64) <= 1.0):
        raise ValueError(f"keep (share of w's damping kept) must lie in [0, 1], got {np.asarray(keep).tolist()}")


# ----------------------------------------------------------------------------- open loop
def _open_loop_act(settings, cstate, obs, nominal, key):
    return jnp.full_like(obs.rho, nominal.h_bar), cstate


def open_loop() -> Controller:
    """The uncontrolled system: h = h_bar everywhere."""
    return Controller(settings=(), act_fn=_open_loop_act, name="open_loop")


# ----------------------------------------------------------------------------- Lyapunov
@struct.dataclass
class LyapunovSettings:
    k: Array  # decay gain of v~, dimensionless (> 0)
    keep: Array  # share of w's own damping the law keeps, in [0, 1] (0: the paper's law cancels it)


def lyapunov_input(rho_t: Array, v_t: Array, k: Array, lm: LinearModel, keep: Array | float = 0.0) -> Array:
    """The Lyapunov law on deviations: U = ((1 - keep) w - k v~)/V_h (s); with ``keep`` = 0 (the paper's)
    U = (w - k v~)/V_h = ((1 - k) v~ - V_rho rho~)/V_h.

    It turns the common source (-w + V_h U)/tau_mix of the linearised model into (-keep w - k v~)/tau_mix:
    the paper's law cancels w's damping (density then leaves only by transport), ``keep`` > 0 keeps that share
    of it (docs/model.md section 20: a design parameter the fair comparison tunes).
    """
    return ((1 - keep) * riemann_w(rho_t, v_t, lm) - k * v_t) / lm.V_h


def lyapunov_law(rho: Array, v: Array, k: Array, lm: LinearModel, keep: Array | float = 0.0) -> Array:
    """The Lyapunov law on the fields rho (veh/m), v (m/s): h = h_bar + U (s), unsaturated."""
    return lm.h_bar + lyapunov_input(rho - lm.rho_bar, v - lm.v_bar, k, lm, keep)


def lyapunov_h(rho_t: Array, v_t: Array, settings, lm: LinearModel, k: Array | None = None) -> Array:
    """h = h_bar + U from deviations, with the gain ``k`` (default ``settings.k``) and ``settings.keep``. The
    optimisation barrier keeps XLA from fusing the law with whatever produced the deviations and the
    coefficients, so that ``lyapunov`` and ``backstepping(0)`` compile the law identically and agree bit for
    bit on CPU (without it they differ by 1 ulp at a few nodes)."""
    k = settings.k if k is None else k
    rho_t, v_t, k, keep, lm = jax.lax.optimization_barrier((rho_t, v_t, k, settings.keep, lm))
    return lm.h_bar + lyapunov_input(rho_t, v_t, k, lm, keep)


def _lyapunov_act(settings, cstate, obs, nominal, key):
    lm = linearize(nominal)
    return lyapunov_h(obs.rho - lm.rho_bar, obs.v - lm.v_bar, settings, lm), cstate


def _lyapunov_nonlinear_act(settings, cstate, obs, nominal, key):
    _, v_bar = equilibrium(nominal)
    v_target = obs.v - settings.k * (obs.v - v_bar)
    # speed matching: V(rho, h) = v_target, i.e. h_mix(h) = (1/rho - l)/v_target
    hm = (1.0 / obs.rho - nominal.l) / jnp.maximum(v_target, 1e-6)
    c, b = fd.mix_coefficients(nominal)
    hm = jnp.minimum(hm, 0.999 * c / b)  # h_mix saturates at c/b: beyond it no h exists
    return fd.h_mix_inv(hm, nominal), cstate


def lyapunov(k: float | Array = 1.0, nonlinear: bool = False, keep: float | Array = 0.0) -> Controller:
    """Lyapunov in-domain feedback (docs/model.md section 7), gain ``k`` > 0 (dimensionless); ``keep``: the
    share of w's damping kept, in [0, 1] (``lyapunov_input``; 0: the paper's law; not with ``nonlinear``).

    h = h_bar + ((1 - k) v~ - V_rho rho~)/V_h with the nominal equilibrium coefficients; in the
    linearised closed loop v~ decays at rate k/tau_mix (1/s) along its characteristic.
    ``nonlinear=True`` uses the speed-matching variant h = h_mix^{-1}((1/rho - l)/(v - k v~))
    (when v - k v~ <= 0 or the required h_mix exceeds its supremum c/b it asks for a very large
    gap, which the actuator bound turns into h_max).
    """
    _check_setting("lyapunov gain k", k)
    _check_share(keep)
    act = _lyapunov_nonlinear_act if nonlinear else _lyapunov_act
    k, keep = jnp.broadcast_arrays(jnp.asarray(k, float), jnp.asarray(keep, float))  # a batch of k: keep's too
    return Controller(settings=LyapunovSettings(k=k, keep=keep), act_fn=act,
                      name="lyapunov_nl" if nonlinear else "lyapunov")


# ----------------------------------------------------------------------------- predictor
@struct.dataclass
class BacksteppingSettings:
    k: Array  # Lyapunov gain of the target law, dimensionless
    delay: Array  # assumed input delay D_ctrl, s (may differ from the plant's)
    keep: Array  # share of w's damping the target law keeps, in [0, 1] (``lyapunov_input``)


def predict(rho_t: Array, v_t: Array, sent: delay_buffer.DelayBuffer, d: Array,
            lm: LinearModel, bounded: bool | None = None) -> tuple[Array, Array]:
    """Deviation state (veh/m, m/s) predicted ``d`` steps ahead by the discrete linear model.

    At t_n the buffer holds h^{n-1} (``read(sent, 0)``), h^{n-2}, ...; a plant with delay d
    applies h^{n-d+j} at step n+j, so step j = 0..d-1 of the prediction uses
    ``read(sent, d-1-j)``. The result is x^{n+d} exactly (to rounding) when the plant is the
    discrete linear model (``TrafficParams(model="linear")``) with delay d.

    Cost: d sequential ``linear_step``s, each O(n_points) (about 20 flops per node), so
    O(d n_points) per control step and no state carried between control steps. This is the
    cheapest exact predictor for the discrete model: any exact one reads the d n_points pending
    inputs, and the alternatives (a dense/banded d-step transition matrix: O(n_points^2) or
    O(d n_points) flops plus O(d^2 n_points) for the input convolution; or a recursively updated
    prediction: O(n_points) but it accumulates rounding through the open-loop-unstable model
    and does not correct itself from the measurement) are not better. ``d`` is traced: under
    ``vmap`` with different assumed delays the loop runs max(d) iterations, masked.

    ``bounded`` (static; default: on an accelerator, ``jax.default_backend() != "cpu"``): run the buffer's
    capacity (``sent.size - 1`` >= d) iterations, those from d on masked (a select), instead of a loop whose
    trip count is traced (on a GPU each iteration of such a loop waits for the host to read its condition).
    The same values, bit for bit on a CPU (tests/test_baselines.py); on a CPU the traced trip count is
    cheaper when d is below the capacity.
    """
    def body(j, carry):
        r, v = carry
        U = delay_buffer.read(sent, d - 1 - j) - lm.h_bar
        return linear_step(r, v, U, lm)

    if bounded is None:
        bounded = jax.default_backend() != "cpu"
    if not bounded:
        return jax.lax.fori_loop(0, d, body, (rho_t, v_t))

    def masked(j, carry):
        new = body(j, carry)
        return jax.tree.map(lambda x, y: jnp.where(j < d, x, y), new, carry)

    return jax.lax.fori_loop(0, sent.size - 1, masked, (rho_t, v_t))


def assumed_delay_steps(delay: Array, sent: delay_buffer.DelayBuffer, nominal: TrafficParams) -> Array:
    """The controller's assumed delay in steps: round(D_ctrl/dt), clipped to [0, capacity]
    (``max_delay_steps`` of the plant's buffer, the oldest input still stored)."""
    d = jnp.round(delay / nominal.dt).astype(jnp.int32)
    return jnp.clip(d, 0, sent.size - 1)


def _checked_gain(settings) -> Array:
    """The gain k, or NaN if a traced setting the constructor could not check is invalid (a non-finite gain, a
    NaN or negative assumed delay): the law then returns NaN, which ``sim.plant`` reports as
    ``Divergence.CONTROL`` (``sim.outcome``). (A select on the scalar gain, so the law's arithmetic is untouched.)"""
    ok = jnp.isfinite(settings.delay) & (settings.delay >= 0)
    return jnp.where(ok, settings.k, jnp.nan)


def _backstepping_act(settings, cstate, obs, nominal, key):
    lm = linearize(nominal)
    d = assumed_delay_steps(settings.delay, obs.sent, nominal)
    r_hat, v_hat = predict(obs.rho - lm.rho_bar, obs.v - lm.v_bar, obs.sent, d, lm)
    return lyapunov_h(r_hat, v_hat, settings, lm, _checked_gain(settings)), cstate


# ----------------------------------------------------------------------------- recursive predictor
ANCHOR_EVERY = 50  # steps between exact re-anchorings of the recursive predictor (5 s at dt = 0.1 s)


@struct.dataclass
class RecursivePrediction:
    """State of the recursive predictor: the last prediction (deviations, shape (2, n_points)), the
    last measured deviation state (2, n_points) and the number of calls."""

    pred: Array
    last: Array
    step: Array


def _recursive_init(settings, obs, nominal):
    z = jnp.zeros((2,) + obs.rho.shape, obs.rho.dtype)
    return RecursivePrediction(pred=z, last=z, step=jnp.zeros((), jnp.int32))


def predict_recursive(rho_t: Array, v_t: Array, sent: delay_buffer.DelayBuffer, d: Array, lm: LinearModel,
                      cs: RecursivePrediction, anchor_every: int = ANCHOR_EVERY
                      ) -> tuple[Array, Array, RecursivePrediction]:
    """The d-step prediction of ``predict``, updated recursively and corrected from the measurement,
    re-anchored on the exact one every ``anchor_every`` steps:

        P_n = A P_{n-1} + B u^{n-1} + e_n,   e_n = x^n - (A x^{n-1} + B u^{n-1-d})
        P_n = predict(x^n, ...)   at n = 0 mod anchor_every (n = 0 included) and for d = 0

    (e_n: the innovation, the measured state minus the model's one-step prediction; the exact
    predictor would add A^d e_n.) On the discrete linear plant e_n is rounding, so P_n equals
    ``predict``'s x^{n+d} up to rounding grown by the model over at most ``anchor_every`` steps;
    on the nonlinear plant it misses (A^d - I) e of the innovations since the last anchor
    (measured against the exact prediction: docs/model.md section 13.5). Cost: two linear steps per control
    step plus d per anchor; under ``vmap`` the exact loop runs only on anchor steps, which every
    environment of a batch shares (same step counter), so it is skipped at the other steps.
    """
    n = cs.step
    anchor = (n % anchor_every == 0) | (d == 0)
    # (a traced trip count: under vmap the environments share the anchor steps, so the loop is skipped at the
    # others; a bound of the capacity would run it every step)
    exact_r, exact_v = predict(rho_t, v_t, sent, jnp.where(anchor, d, 0), lm, bounded=False)
    h_bar = lm.h_bar
    r1, v1 = linear_step(cs.pred[0], cs.pred[1], delay_buffer.read(sent, 0) - h_bar, lm)
    m_r, m_v = linear_step(cs.last[0], cs.last[1], delay_buffer.read(sent, d) - h_bar, lm)
    rec_r, rec_v = r1 + (rho_t - m_r), v1 + (v_t - m_v)
    r_hat, v_hat = jnp.where(anchor, exact_r, rec_r), jnp.where(anchor, exact_v, rec_v)
    new = RecursivePrediction(pred=jnp.stack([r_hat, v_hat]), last=jnp.stack([rho_t, v_t]), step=n + 1)
    return r_hat, v_hat, new


def _backstepping_recursive_act(settings, cstate, obs, nominal, key):
    lm = linearize(nominal)
    d = assumed_delay_steps(settings.delay, obs.sent, nominal)
    r_hat, v_hat, cstate = predict_recursive(obs.rho - lm.rho_bar, obs.v - lm.v_bar, obs.sent, d, lm, cstate)
    return lyapunov_h(r_hat, v_hat, settings, lm, _checked_gain(settings)), cstate


def check_assumed_delay(controller: Controller | None, params: TrafficParams) -> None:
    """``ValueError`` if ``controller`` is a backstepping law whose (concrete) assumed delay, in steps of
    ``params.dt``, exceeds the plant's delay buffer (``max_delay_steps``): it would be clipped to the buffer's
    capacity in silence. Other controllers, traced settings and batched ``params`` are not checked."""
    if controller is None or not isinstance(controller.settings, BacksteppingSettings):
        return
    d, dt = concrete(controller.settings.delay), concrete(params.dt)
    if d is None or dt is None or np.ndim(dt) or not np.all(np.isfinite(d)):
        return
    steps = int(np.max(np.round(np.asarray(d, np.float64) / float(dt))))
    if steps > params.max_delay_steps:
        raise ValueError(f"backstepping: the assumed delay {float(np.max(d)):g} s is {steps} steps of "
                         f"dt = {float(dt):g} s, beyond the plant's delay buffer "
                         f"(max_delay_steps = {params.max_delay_steps}, "
                         f"{params.max_delay_steps * float(dt):g} s); raise max_delay_steps or lower the delay")


def backstepping(delay: float | Array = 4.0, k: float | Array = 1.0, recursive: bool = False,
                 keep: float | Array = 0.0) -> Controller:
    """Delay-compensated (predictor / backstepping) feedback, docs/model.md section 8.

    Applies the Lyapunov law with gain ``k`` to the state predicted ``delay`` seconds (D_ctrl)
    ahead by the discrete linearised model with nominal parameters over the inputs already sent
    (see ``predict``). D_ctrl is its own setting, independent of the plant's delay; it is
    rounded to a whole number of steps; ``simulate`` refuses one beyond the plant's buffer capacity
    (``max_delay_steps``; ``check_assumed_delay``; a traced one is clipped to it). With delay = 0 it
    equals ``lyapunov(k)`` exactly.

    ``recursive=True``: the cheaper ``predict_recursive`` (one linear step per control step plus an
    exact re-anchoring every ``ANCHOR_EVERY`` steps) instead of d linear steps per control step;
    equal to the exact predictor on the linear plant and for delay = 0, close to it otherwise.
    ``keep``: the share of w's damping the target law keeps, in [0, 1] (``lyapunov_input``; 0: the paper's).
    """
    _check_setting("assumed delay", delay, minimum=0.0)
    _check_setting("backstepping gain k", k)
    _check_share(keep)
    shape = jnp.broadcast_shapes(jnp.shape(k), jnp.shape(delay), jnp.shape(keep))  # keep follows a batch
    settings = BacksteppingSettings(k=jnp.asarray(k, float), delay=jnp.asarray(delay, float),
                                    keep=jnp.broadcast_to(jnp.asarray(keep, float), shape))
    if recursive:
        return Controller(settings=settings, act_fn=_backstepping_recursive_act, init_fn=_recursive_init,
                          name="backstepping")
    return Controller(settings=settings, act_fn=_backstepping_act, name="backstepping")
