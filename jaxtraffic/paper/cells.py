"""The robustness map's cells at two horizons (issue 47 item 3; docs/model.md section 18).

One map rollout runs to the map's horizon (``EvalConfig.robust_horizon_s``, 600 s) and also yields the paper's
column, the state at the paper's horizon (300 s): it records its states every ``snapshot_every`` steps, a stride
dividing both horizons, so that the state at 300 s is among the (two, at 300 s and 600 s) records.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxtraffic.sim.metrics import VEH_PER_KM

SNAPSHOTS_MAX = 64  # the most states a map rollout records to hold the one at the paper's horizon


def snapshot_every(n_paper: int, n_map: int) -> int:
    """The recording stride (steps) of a map rollout of ``n_map`` steps whose records hold the state at step
    ``n_paper`` (the paper's horizon): their greatest common divisor; 0 (no record) when that state is the final
    one or lies beyond it, or when it would take more than ``SNAPSHOTS_MAX`` records."""
    if n_paper >= n_map:
        return 0
    g = math.gcd(n_paper, n_map)
    return g if n_map // g <= SNAPSHOTS_MAX else 0


def paper_column(res: Any, n_paper: int, every: int, cells: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The map's cells at the paper's horizon (step ``n_paper``) of the map rollout ``res`` recorded every
    ``every`` steps (``snapshot_every``; 0: the final state is the paper's when the horizons agree, else NaN):
    "paper_rho_L2", "paper_rho_spatial_std" (veh/km) and "paper_diverged" (diverged at a step < ``n_paper``,
    from ``cells``'s "diverged" and "diverged_step")."""
    shape = cells["diverged"].shape
    div = cells["diverged"] & (cells["diverged_step"] < n_paper)
    if every:
        k = n_paper // every
        rho = np.asarray(res.trajectory.rho)[:, k]
        l2 = np.asarray(res.trajectory.rho_L2)[:, k].reshape(shape)
        std = VEH_PER_KM * np.std(rho, axis=-1).reshape(shape)
    elif n_paper == int(np.max(res.final.step)):
        l2, std = cells["final_rho_L2"], cells["final_rho_spatial_std"]
    else:
        l2 = std = np.full(shape, np.nan)
    return {"paper_rho_L2": l2, "paper_rho_spatial_std": std, "paper_diverged": div}
