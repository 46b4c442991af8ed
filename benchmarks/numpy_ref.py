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


def make_step(p: TrafficParams, k: float = 1.0, dtype=np.float32):
    """``step(rho, v) -> (rho, v)``: one closed-loop step of a (batch, n) state, in numpy."""
    f = lambda x: dtype(float(x))  # noqa: E731
    lm = linearize(p)
    rho_bar, v_bar = (f(x) for x in equilibrium(p))
    c, b = (f(x) for x in fd.mix_coefficients(p))
    a, l_, dt, inv_dx = f(p.alpha), f(p.l), f(p.dt), f(1.0 / p.dx)
    inv_tau = f(p.alpha / p.tau_acc + (1.0 - p.alpha) / p.tau_m)
    V_rho, V_h, h_bar = f(lm.V_rho), f(lm.V_h), f(lm.h_bar)
    h_min, h_max, q_in = f(p.h_min), f(p.h_max), f(p.q_in)

    def step(rho, v):
        rt, vt = rho - rho_bar, v - v_bar
        h = np.clip(h_bar + ((1 - k) * vt - V_rho * rt) / V_h, h_min, h_max)
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
