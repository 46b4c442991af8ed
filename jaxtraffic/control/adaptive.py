"""Adaptive delay compensation: backstepping whose model's ACC share alpha is estimated online.

The estimator (docs/model.md section 18) fits alpha to the speed
equation, whose relaxation term (V(rho, h; alpha) - v) / tau_mix(alpha) and characteristic speed
depend on it. At control step n the controller knows x^{n-1} = (rho, v) (its previous observation),
the time gap the plant applied over step n-1 (``read(sent, d)``, d: the delay it is told) and x^n.
With F(x, h; a) the speed field after one step of the model (``solver.arz_step`` on the
controller's grid with ACC share a), the residual and its sensitivity at the estimate a_n are

    r_i = v_i^n - F_i(x^{n-1}, h; a_n),   J_i = dF_i/da (forward-mode, one ``jax.jvp``)

and a recursive Gauss-Newton (scalar recursive least squares with exponential forgetting lam)
update with projection onto [ALPHA_MIN, 1] = [0.01, 1] follows (at alpha = 0 the time gap has no
effect on the speed, V_h = 0, and the Lyapunov law, which divides by V_h, is undefined):

    R_n = lam R_{n-1} + <J^2>_w,   a_{n+1} = clip(a_n + gamma <J r>_w / max(R_n, R_min), 0.01, 1)

<.>_w is the mean over the nodes with weights w_i, which weigh down nodes with a steep density
gradient (the one-step model is least right at a shock: w_i = 1 / (1 + (|rho_{i+1} - rho_{i-1}| /
(2 shock_scale))^2)); the inlet node is excluded. R_min ((m/s)^2, ``min_info``) is a floor under R so
that the gain does not wind up when the state carries no information (at the plant's equilibrium
J ~ 0 and r is rounding). ``gamma`` is 1 (adapting) or 0 (the estimate stays alpha0).

The law: backstepping (``control.baselines``) with the nominal's alpha replaced by the estimate,
i.e. the linearisation, the predictor and the Lyapunov law all use a_n (certainty equivalence). It
linearises about the nominal equilibrium, which the estimated plant holds under the time gap
h* = h_mix^{-1}(h_mix(h_bar; alpha_nominal); a_n) (``hold_target``, the default; ``estimated_model``), or
about the estimated model's equilibrium at h_bar (the plant's own once a_n = alpha, where its open
loop would rest).

Assumptions: the plant's alpha is constant or slowly varying against the forgetting window
(1/(1 - lam) steps); the delay the controller is told is the plant's (a wrong delay misaligns the
input in the regression and biases the estimate); the other physical constants (tau_acc, tau_m,
h_m, l, q_in) are known; measurements are noise-free full-state (rho, v at every node of the
controller's grid). The one-step model is the controller's own discretisation, so on a finer plant
the residual carries the discretisation error as well (small where the state is smooth; the
shock weights keep it from dominating; where the plant keeps shocks the controller's grid does not
resolve, the estimate drifts: docs/model.md section 18.1, known limits).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.control.base import Controller
from jaxtraffic.control.baselines import (
    _check_setting,
    _check_share,
    _checked_gain,
    assumed_delay_steps,
    lyapunov_h,
    predict,
)
from jaxtraffic.model import delay as delay_buffer
from jaxtraffic.model import fundamental as fd
from jaxtraffic.model.linear import linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.model.solver import arz_step
from jaxtraffic.platform.tracing import is_traced

Array = jax.Array
ALPHA_MIN = 0.01  # lower end of the projection: at alpha = 0 the input has no effect (V_h = 0)
MAX_DELAY_S = 3600.0  # s: an assumed delay beyond an hour is no vehicle's (the paper's are a few seconds)
# each setting's valid range: (lo, lo included, hi, hi included); NaN alpha0: the nominal's alpha
RANGES = {"assumed delay": (0.0, True, MAX_DELAY_S, True), "alpha0": (0.0, True, 1.0, True),
          "forgetting": (0.0, False, 1.0, True), "shock_scale": (0.0, False, None, True),
          "min_info": (0.0, False, None, True), "resid_scale": (0.0, True, None, True)}
UNITS = {"assumed delay": " s", "shock_scale": " veh/m", "min_info": " (m/s)^2", "resid_scale": " m/s"}


def _check_range(name: str, value: float | Array) -> None:
    """``ValueError`` with the valid range (``RANGES``) unless a concrete setting lies in it (NaN alpha0: the
    default); a traced one is not checked (``_check_setting``)."""
    if is_traced(value):
        return
    if name != "alpha0" or not np.all(np.isnan(np.asarray(value, np.float64))):
        _check_setting(name, value)
    lo, lo_in, hi, hi_in = RANGES[name]
    x = np.asarray(value, np.float64)
    x = x[~np.isnan(x)] if name == "alpha0" else x
    ok = np.all(x >= lo if lo_in else x > lo) and (hi is None or np.all(x <= hi if hi_in else x < hi))
    if not ok:
        close = "]" if hi_in and hi is not None else ")"
        span = f"{'[' if lo_in else '('}{lo:g}, {'inf' if hi is None else f'{hi:g}'}{close}{UNITS.get(name, '')}"
        raise ValueError(f"adaptive_backstepping: {name} must lie in {span}, got {x.tolist()}")


@struct.dataclass
class AdaptiveSettings:
    """Settings of adaptive backstepping (all traced).

    k: Lyapunov gain (dimensionless); delay: the delay it is told, s; alpha0: the initial estimate
    (NaN: the nominal's alpha); forgetting: lam in (0, 1] per control step; adapt: 1 to adapt, 0 to
    keep alpha0; shock_scale: density jump (veh/m) above which a node's weight falls off;
    min_info: floor under R, (m/s)^2 (> 0): below it the state carries too little information and the
    gain no longer grows; hold_target: 1 to linearise about the nominal equilibrium (held by the time
    gap h* of the estimated plant), 0 about the estimated plant's equilibrium at h_bar.
    """

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> AdaptiveSettings: ...

    k: Array
    delay: Array
    alpha0: Array
    forgetting: Array
    adapt: Array
    shock_scale: Array
    min_info: Array
    hold_target: Array
    resid_scale: Array
    keep: Array  # share of w's damping the target law keeps, in [0, 1] (``baselines.lyapunov_input``)


@struct.dataclass
class EstimatorState:
    """The estimator's state: the estimate alpha_hat, the information R ((m/s)^2, the forgetting sum
    of the weighted mean squared sensitivity), the previous observation (veh/m, m/s, on the
    controller's grid) and whether there is one."""

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> EstimatorState: ...

    alpha_hat: Array
    info: Array
    prev_rho: Array
    prev_v: Array
    started: Array


def initial_estimate(settings: AdaptiveSettings, nominal: TrafficParams) -> Array:
    """alpha0, or the nominal's alpha where alpha0 is NaN, projected onto [ALPHA_MIN, 1]."""
    a0 = jnp.asarray(settings.alpha0)
    return jnp.clip(jnp.where(jnp.isnan(a0), jnp.asarray(nominal.alpha, a0.dtype), a0), ALPHA_MIN, 1.0)


def _init(settings: AdaptiveSettings, obs, nominal: TrafficParams) -> EstimatorState:
    zero = jnp.zeros((), obs.rho.dtype)
    return EstimatorState(alpha_hat=initial_estimate(settings, nominal).astype(obs.rho.dtype), info=zero,
                          prev_rho=obs.rho, prev_v=obs.v, started=jnp.zeros((), bool))


def shock_weights(rho: Array, scale: Array) -> Array:
    """Per-node weights 1 / (1 + (|rho_{i+1} - rho_{i-1}| / (2 scale))^2), the inlet node 0 (its
    speed is extrapolated, not modelled) weighted 0; one-sided differences at the outlet."""
    grad = jnp.abs(cast(Array, jnp.gradient(rho)))  # one axis: one array, not a list of them
    w = 1.0 / (1.0 + (grad / scale) ** 2)
    return w.at[0].set(0.0)


def estimator_update(settings: AdaptiveSettings, cs: EstimatorState, rho: Array, v: Array, h_applied: Array,
                     nominal: TrafficParams) -> EstimatorState:
    """One recursive Gauss-Newton step of the estimate from (x^{n-1} in ``cs``, the applied gap
    ``h_applied`` (s), x^n = (rho, v)) (module docstring). Before the first pair no update."""
    def speed(a):
        return arz_step(cs.prev_rho, cs.prev_v, h_applied, nominal, a)[1]

    a = cs.alpha_hat
    v_pred, sens = jax.jvp(speed, (a,), (jnp.ones_like(a),))
    w = shock_weights(cs.prev_rho, settings.shock_scale)
    robust = settings.resid_scale > 0  # Cauchy weights on the residual (a robust fit); 0: off
    scale = jnp.where(robust, settings.resid_scale, 1.0)
    w = jnp.where(robust, w / (1.0 + ((v - v_pred) / scale) ** 2), w)
    ok = jnp.all(jnp.isfinite(v_pred)) & jnp.all(jnp.isfinite(sens)) & cs.started
    resid = jnp.where(ok, v - v_pred, 0.0)
    sens = jnp.where(ok, sens, 0.0)
    w_sum = jnp.maximum(jnp.sum(w), 1.0)
    info = settings.forgetting * cs.info + jnp.sum(w * sens * sens) / w_sum
    denom = jnp.maximum(info, settings.min_info)
    step = jnp.sum(w * sens * resid) / w_sum / denom
    a_new = jnp.clip(a + settings.adapt * step, ALPHA_MIN, 1.0)
    a_new = jnp.where(settings.adapt > 0, a_new, a)  # adaptation off: the estimate stays, bit for bit
    return cs.replace(alpha_hat=a_new.astype(a.dtype), info=info, prev_rho=rho, prev_v=v, started=jnp.ones((), bool))


def estimated_model(settings: AdaptiveSettings, nominal: TrafficParams, alpha_hat: Array) -> TrafficParams:
    """The model the law uses: ``nominal`` with ACC share ``alpha_hat``, linearised about its equilibrium at
    h_bar (the estimated plant's own), or, with ``hold_target``, about the nominal equilibrium
    (rho_bar, v_bar), which the estimated plant holds under the time gap h* = h_mix^{-1}(h_mix(h_bar; alpha);
    alpha_hat) (docs/model.md section 12), clipped to [h_min, h_max]."""
    model = nominal.replace(alpha=alpha_hat)
    h_star = fd.h_mix_inv(fd.h_mix(nominal.h_bar, nominal), model)
    c, b = fd.mix_coefficients(model)
    ok = fd.h_mix(nominal.h_bar, nominal) < c / b
    h_star = jnp.clip(jnp.where(ok, h_star, nominal.h_max), nominal.h_min, nominal.h_max)
    return model.replace(h_bar=jnp.where(settings.hold_target > 0, h_star, nominal.h_bar))


def _act(settings: AdaptiveSettings, cs: EstimatorState, obs, nominal: TrafficParams, key):
    d = assumed_delay_steps(settings.delay, obs.sent, nominal)
    cs = estimator_update(settings, cs, obs.rho, obs.v, delay_buffer.read(obs.sent, d), nominal)
    lm = linearize(estimated_model(settings, nominal, cs.alpha_hat))
    r_hat, v_hat = predict(obs.rho - lm.rho_bar, obs.v - lm.v_bar, obs.sent, d, lm)
    return lyapunov_h(r_hat, v_hat, settings, lm, _checked_gain(settings)), cs


def adaptive_backstepping(delay: float | Array = 4.0, k: float | Array = 1.0, *, alpha0: float | Array = float("nan"),
                          forgetting: float | Array = 0.99, adapt: bool | Array = True,
                          shock_scale: float | Array = 2e-3, min_info: float | Array = 1e-6,
                          hold_target: bool | Array = True, resid_scale: float | Array = 0.0,
                          keep: float | Array = 0.0) -> Controller:
    """Backstepping with its model's ACC share estimated online (module docstring). Each setting is checked
    against its range, ``RANGES``: the delay in [0, 3600] s, the scales > 0.

    Args:
        delay: the delay it is told (s), as ``backstepping``'s (``control.tell_delay`` sets it).
        k: Lyapunov gain (dimensionless).
        alpha0: initial estimate in [0, 1] (default NaN: the nominal's alpha).
        forgetting: forgetting factor lam in (0, 1] per control step (memory ~ 1/(1 - lam) steps).
        adapt: False keeps alpha0 (then, told alpha0 = the nominal's alpha and hold_target=False, it equals
            ``backstepping`` to rounding).
        shock_scale: density difference across a node (veh/m) at which its weight halves (> 0).
        min_info: floor under the information R, (m/s)^2 (> 0; module docstring).
        hold_target: linearise about the nominal equilibrium, held by the estimated plant's time gap h*
            (``estimated_model``; the default: it stabilises 50 of the reference map's 52 controllable
            cells against 43), instead of the estimated plant's own equilibrium at h_bar.
        resid_scale: residual (m/s) at which a node's weight halves (Cauchy weights, a robust fit; the
            default 0 leaves them out, as measured in docs/model.md section 18.1).
        keep: the share of w's damping the target law keeps, in [0, 1] (``baselines.lyapunov_input``; 0: the
            paper's law).
    Returns:
        A ``Controller`` named "adaptive_backstepping"; its state is an ``EstimatorState``.
    """
    _check_setting("backstepping gain k", k)
    _check_share(keep)
    for name, value in (("assumed delay", delay), ("alpha0", alpha0), ("forgetting", forgetting),
                        ("shock_scale", shock_scale), ("min_info", min_info), ("resid_scale", resid_scale)):
        _check_range(name, value)
    as_f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    settings = AdaptiveSettings(k=as_f(k), delay=as_f(delay), alpha0=as_f(alpha0), forgetting=as_f(forgetting),
                                adapt=as_f(adapt),
                                shock_scale=as_f(shock_scale), min_info=as_f(min_info),
                                hold_target=as_f(hold_target), resid_scale=as_f(resid_scale), keep=as_f(keep))
    return Controller(settings=settings, act_fn=_act, init_fn=_init, name="adaptive_backstepping")
