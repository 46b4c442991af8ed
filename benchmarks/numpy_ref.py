"""The paper's closed loop (Lyapunov law, upwind ARZ step, inlet condition) written as plain batched
numpy, float32: the reference that ``bench_sim.py`` times in the same process as ``simulate_batch``.

Per cell update it does the same arithmetic as ``model.solver.arz_step`` (``scheme="upwind"``) with
``control.baselines.lyapunov`` and ``saturate``, on arrays of shape (batch, n_points), one numpy
call per operation (each a pass over the batch); no metrics, no divergence check, no delay buffer
(D = 0), so it is a lower bound on what the same loop costs in numpy.
"""

from __future__ import annotations

import numpy as np

from jaxtraffic import TrafficParams, equilibrium
from jaxtraffic.model import fundamental as fd
from jaxtraffic.model.linear import linearize


def make_step(p: TrafficParams, k: float = 1.0, dtype=np.float32, law=None):
    """``step(rho, v) -> (rho, v)``: one closed-loop step of a (batch, n) state, in numpy; ``law``:
    ``h = law(rho, v)`` before saturation (default: the Lyapunov law with gain ``k``); a law with
    ``law.plant_h`` (a function of the saturated h) applies what that returns (the delay line)."""
    f = lambda x: dtype(float(x))  # noqa: E731
    lm = linearize(p)
    rho_bar, v_bar = (f(x) for x in equilibrium(p))
    c, b = (f(x) for x in fd.mix_coefficients(p))
    a, l_, dt, inv_dx = f(p.alpha), f(p.l), f(p.dt), f(1.0 / p.dx)
    inv_tau = f(p.alpha / p.tau_acc + (1.0 - p.alpha) / p.tau_m)
    V_rho, V_h, h_bar = f(lm.V_rho), f(lm.V_h), f(lm.h_bar)
    h_min, h_max, q_in = f(p.h_min), f(p.h_max), f(p.q_in)

    def lyap(rho, v):
        rt, vt = rho - rho_bar, v - v_bar
        return h_bar + ((1 - k) * vt - V_rho * rt) / V_h

    law = lyap if law is None else law
    plant_h = getattr(law, "plant_h", lambda h: h)

    def step(rho, v):
        h = plant_h(np.clip(law(rho, v), h_min, h_max))
        q = rho * v
        drho = np.zeros_like(rho)
        drho[:, 1:] = (q[:, :-1] - q[:, 1:]) * inv_dx
        inv_rho = 1 / rho
        inv_hm = (a + b * h) / (c * h)
        lam2 = v - inv_rho * inv_hm
        src = ((inv_rho - l_) * inv_hm - v) * inv_tau
        d = (v[:, 1:] - v[:, :-1]) * inv_dx
        vx_b = np.concatenate([d[:, :1], d[:, :-1]], axis=1)
        vx = np.where(lam2[:, :-1] < 0, d, vx_b)
        dv = src.copy()
        dv[:, :-1] -= lam2[:, :-1] * vx
        rho1, v1 = rho + dt * drho, v + dt * dv
        rho1[:, 0] = q_in / v1[:, 0]
        return rho1, v1

    return step


def run(p: TrafficParams, rho0: np.ndarray, v0: np.ndarray, n_steps: int, k: float = 1.0):
    step = make_step(p, k, rho0.dtype.type)
    rho, v = rho0.copy(), v0.copy()
    for _ in range(n_steps):
        rho, v = step(rho, v)
    return rho, v


class _Delayed:
    """A law whose output reaches the plant ``d`` steps later (a ring buffer of sent fields, h_bar before)."""

    def __init__(self, law, d: int, shape, h_bar, dtype):
        self.law, self.d = law, d
        self.buf = np.full((d + 1,) + shape, h_bar, dtype)
        self.head = 0

    def __call__(self, rho, v):
        return self.law(rho, v, self)

    def sent(self, age: int) -> np.ndarray:
        """The field sent ``age`` steps before the last one (0: the last)."""
        return self.buf[(self.head - age) % (self.d + 1)]

    def plant_h(self, h):
        self.head = (self.head + 1) % (self.d + 1)
        self.buf[self.head] = h
        return self.sent(self.d)


def run_controller(name: str, p: TrafficParams, rho0: np.ndarray, v0: np.ndarray, n_steps: int,
                   gains=(0.0, 0.0, 0.0), delay: float = 4.0, k: float = 1.0):
    """``n_steps`` closed-loop steps of ``name`` (open_loop, lyapunov, constant_gains (pointwise law with
    ``gains``), backstepping (assumed delay ``delay`` s = the plant's ``p.delay``)) in batched numpy."""
    dt_ = rho0.dtype.type
    f = lambda x: dt_(float(x))  # noqa: E731
    lm = linearize(p)
    rho_bar, v_bar, h_bar = f(lm.rho_bar), f(lm.v_bar), f(lm.h_bar)
    V_rho, V_h, tau, lam2, dt, dx = (f(x) for x in (lm.V_rho, lm.V_h, lm.tau, lm.lam2, lm.dt, lm.dx))
    e1, e2, e3 = (f(g) for g in gains)
    d_plant = int(round(float(p.delay) / float(p.dt)))
    h_prev = [np.full_like(rho0, h_bar)]

    def open_law(rho, v, buf=None):
        return np.full_like(rho, h_bar)

    def gain_law(rho, v, buf=None):
        h = h_bar + h_bar * (-e1 * (h_prev[0] - h_bar) / h_bar - e2 * (v - v_bar) / v_bar
                             + e3 * (rho - rho_bar) / rho_bar)
        h_prev[0] = np.clip(h, f(p.h_min), f(p.h_max))
        return h

    def linear_step(r, v, U):
        q = v_bar * r + rho_bar * v
        r1 = r.copy()
        r1[:, 1:] -= dt / dx * (q[:, 1:] - q[:, :-1])
        src = (V_rho * r + V_h * U - v) / tau
        fwd = (v[:, 1:] - v[:, :-1]) / dx
        bwd = np.concatenate([fwd[:, :1], fwd[:, :-1]], axis=1)
        vx = np.where(lam2 < 0, fwd, bwd)
        adv = np.zeros_like(v)
        adv[:, :-1] = lam2 * vx
        v1 = v + dt * (src - adv)
        r1[:, 0] = -(rho_bar / v_bar) * v1[:, 0]
        return r1, v1

    def back_law(rho, v, buf):
        d = int(round(delay / float(p.dt)))
        r, u = rho - rho_bar, v - v_bar
        for j in range(d):
            r, u = linear_step(r, u, buf.sent(d - 1 - j) - h_bar)
        return h_bar + ((1 - k) * u - V_rho * r) / V_h

    def lyap_law(rho, v, buf=None):
        return h_bar + ((1 - k) * (v - v_bar) - V_rho * (rho - rho_bar)) / V_h

    law = {"open_loop": open_law, "lyapunov": lyap_law, "constant_gains": gain_law, "backstepping": back_law}[name]
    if d_plant > 0:
        law = _Delayed(law, d_plant, rho0.shape, h_bar, rho0.dtype)
    step = make_step(p, k, rho0.dtype.type, law)
    rho, v = rho0.copy(), v0.copy()
    for _ in range(n_steps):
        rho, v = step(rho, v)
    return rho, v
