"""Convergence of the closed loop's metrics under plant refinement, the controller on its own grid (the study
of docs/model.md section 15 on a tiny road: benchmarks/convergence_study.py does it at full size)."""

import jax
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.control.adapter import ControllerGrid, adapt
from jaxtraffic.sim.initial import paper_initial_condition

GRID = ControllerGrid(21, 0.5, 20)  # the controller: 21 points, 0.5 s
LEVELS = ((41, 1), (81, 2), (161, 4), (321, 8))  # plant points, solver steps per 0.5 s (the CFL bound holds)


def _metrics(scheme: str) -> dict[int, np.ndarray]:
    out = {}
    with jax.enable_x64(True):
        for n, s in LEVELS:
            p = jt.TrafficParams(n_points=n, substeps=s, dt=0.5, scheme=scheme, delay=0.0, max_delay_steps=20)
            rho0, v0 = paper_initial_condition(p, amplitude=0.003, wavenumber=1.0, dtype=np.float64)
            res = jt.simulate(p, adapt(jt.constant_gains(0.0, -0.5, -1.0), GRID, p), n_steps=200, rho0=rho0, v0=v0)
            out[n] = np.array([float(res.metrics[k]) for k in ("final_rho_L2", "J_TTT", "J_comfort")])
    return out


@pytest.mark.parametrize("scheme", ["upwind", "muscl"])
def test_metrics_converge_under_plant_refinement(scheme):
    """A smooth controlled loop (small, long wave, no delay), float64: the density L2 at 100 s, J_TTT and
    J_comfort approach the finest plant's monotonically, at an observed order of at least 0.8 per halving of
    dx (about 1-1.5 measured: the controller's interpolated time gap is first order in the plant's dx)."""
    m = _metrics(scheme)
    ns = [n for n, _ in LEVELS]
    err = np.array([np.abs(m[n] - m[ns[-1]]) / np.abs(m[ns[-1]]) for n in ns[:-1]])  # (levels, metrics)
    assert np.all(err[1:] < err[:-1]), err
    orders = np.log2(err[:-1] / err[1:])
    assert np.all(orders >= 0.8), orders
    assert np.all(err[-1] < 0.02), err  # 161 points are within 2 % of 321
