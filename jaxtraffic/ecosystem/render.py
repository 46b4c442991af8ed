"""``render_mode="rgb_array"`` of the Gymnasium environments: the episode's density as a space-time picture.

A frame is the density deviation rho - rho_bar over the episode so far (time to the right over the
whole horizon, position upwards over the road), coloured like the density column of the paper's
space-time figures (``paper.plotting.plot_spacetime``: ``RdBu_r``, centred on the nominal
equilibrium, red = denser); steps not yet reached are grey. Frames have a fixed size, so that a
video recorder (Gymnasium's ``RecordVideo``) can stack them. Plain numpy and a matplotlib colour map:
about a millisecond a frame, no figure is drawn.
"""

from __future__ import annotations

import numpy as np
from matplotlib import colormaps

FRAME = (200, 400)  # (height, width) in pixels
CMAP = "RdBu_r"  # the density column of paper.plotting.plot_spacetime
NOT_YET = (0.85, 0.85, 0.85)  # grey: steps of the horizon the episode has not reached


class History:
    """The density of ``num_envs`` episodes, step by step (veh/m): row ``t`` of an environment holds its
    density after ``t`` steps of the current episode, NaN where not reached yet."""

    def __init__(self, num_envs: int, horizon: int, n_points: int):
        self.rho = np.full((num_envs, horizon + 1, n_points), np.nan, np.float32)
        self.t = np.zeros(num_envs, np.int64)

    def start(self, envs: np.ndarray, rho: np.ndarray) -> None:
        """New episodes in the environments ``envs`` (indices), starting from densities ``rho`` (k, n)."""
        self.rho[envs] = np.nan
        self.rho[envs, 0] = rho
        self.t[envs] = 0

    def record(self, envs: np.ndarray, rho: np.ndarray) -> None:
        """One more step of the environments ``envs``, ending at densities ``rho`` (k, n)."""
        self.t[envs] = np.minimum(self.t[envs] + 1, self.rho.shape[1] - 1)
        self.rho[envs, self.t[envs]] = rho


def spacetime_rgb(history: np.ndarray, rho_bar: float, limit: float | None = None,
                  size: tuple[int, int] = FRAME) -> np.ndarray:
    """The picture of one episode's ``history`` (steps x points, veh/m; NaN: not reached), shape
    (height, width, 3), uint8. ``limit``: the deviation (veh/m) at the ends of the colour scale
    (default 10 % of ``rho_bar``, veh/m)."""
    history = np.asarray(history, np.float32)
    steps, points = history.shape
    height, width = size
    cols = np.minimum(np.arange(width) * steps // width, steps - 1)
    rows = np.minimum(np.arange(height)[::-1] * points // height, points - 1)  # the inlet at the bottom
    field = history[cols][:, rows].T  # (height, width)
    lim = 0.1 * rho_bar if limit is None else limit
    rgba = colormaps[CMAP](np.clip(0.5 + (np.nan_to_num(field, nan=rho_bar) - rho_bar) / (2.0 * lim), 0.0, 1.0))
    rgb = rgba[..., :3]
    rgb[np.isnan(field)] = NOT_YET
    return (rgb * 255.0 + 0.5).astype(np.uint8)
