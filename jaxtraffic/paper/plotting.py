"""Figures of the paper's section 4 (docs/model.md section 11) from plain numpy arrays.

Every function takes numpy arrays (no rollout objects) and returns a matplotlib figure, drawn
without pyplot (no backend switch: usable in a notebook, where it displays itself); given a path it
also writes the figure there, in the format the path's suffix names (``.png``, ``.pdf``, ``.svg``, ...; a suffix
matplotlib cannot write is a ``ValueError``: ``io.drawing.figure_format``). ``plot_reward`` draws into an ``ax=``
of yours, the multi-panel ones into a ``fig=`` (a ``Figure`` or a ``SubFigure``, e.g. from ``fig.subfigures``).

Units on the axes: x in m, t in s, density in veh/km, speed in m/s, time gap in s. Space-time maps
use a diverging colour map centred on the equilibrium value with symmetric, robust limits (the
99.5th percentile of |deviation| over all panels of a column; one colour bar per column, ``COLOUR_LEVELS``
colours), so the stop-and-go waves are visible and the controllers are comparable.

Functions:
    plot_learning_curve: paper fig. 3a (from ``runs.curve``).
    plot_reward: paper fig. 3b (reward over time).
    plot_spacetime: paper figs. 4, 5, 7 (rho, v, h over x, t).
    plot_l2_norms: paper figs. 6, 8 (L2 norms over time).
    plot_l2_panels: several L2 comparisons side by side.
    plot_robustness_map: final density L2 heatmaps.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib import colormaps, colors, ticker
from matplotlib.axes import Axes
from matplotlib.figure import Figure, SubFigure

from jaxtraffic.io.drawing import finish_figure, new_figure
from jaxtraffic.paper import laws
from jaxtraffic.runs.curve import plot_learning_curve, read_learning_curve
from jaxtraffic.sim.metrics import REWARD_TARGET, VEH_PER_KM

__all__ = ["plot_l2_norms", "plot_l2_panels", "plot_learning_curve", "plot_reward", "plot_robustness_map",
           "plot_spacetime", "read_learning_curve"]

# colours of each space-time colour map: steps of 1/32 of a column's half range, finer than the eye reads on
# a screen, and flat bands that a PNG stores in a third of the bytes of a continuous map
COLOUR_LEVELS = 64


def _style(label: str) -> dict:
    """A registered law's line style (``paper.laws``: the same in every figure), matched by its name or its
    legend label at the start of ``label`` (the longest match: "Lyapunov k 3" is not "Lyapunov"); {} for any
    other."""
    best: tuple[int, dict] = (0, {})
    for key, law in laws.LAWS.items():
        for prefix in (key, laws.short_label(key)):
            if law.style and label.startswith(prefix) and len(prefix) > best[0]:
                best = (len(prefix), dict(law.style))
    return best[1]


def _mean_band(y: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(mean, min, max) over the leading axis of a (S, T) array; (y, None, None) for (T,)."""
    y = np.asarray(y, float)
    if y.ndim == 1:
        return y, None, None
    if y.shape[0] == 1:
        return y[0], None, None
    return np.mean(y, axis=0), np.min(y, axis=0), np.max(y, axis=0)


# ----------------------------------------------------------------------------- reward over time
def plot_reward(png_path: str | Path | None, t: np.ndarray, series: Mapping[str, np.ndarray],
                title: str = "Reward over time (paper fig. 3b)",
                markers: Mapping[str, float] | None = None, *, ax: Axes | None = None) -> Figure | SubFigure:
    """Reward r(t) of several controllers; plotted as -r on a log axis (r <= 0 always). Drawn into
    ``ax`` if given (else a new figure); returns the figure, saved at ``png_path`` if given.

    ``series``: label -> array (T,) or (S, T) (several seeds: mean with a min-max band).
    ``markers``: label -> time (s) at which that run diverged (drawn as a cross).
    """
    if ax is None:
        ax = new_figure(figsize=(8.5, 4.6)).subplots()
    fig = ax.figure
    floor = 1e-8
    for i, (label, y) in enumerate(series.items()):
        m, lo, hi = _mean_band(-np.asarray(y, float))
        st = _style(label) or dict(color=f"C{i}")
        if "D = 0" in label or "D=0" in label:
            st["ls"] = "--"
        ax.plot(t, np.maximum(m, floor), lw=max(2.8 - 0.4 * i, 1.2), label=label, **st)
        if lo is not None and hi is not None:  # (both or neither)
            ax.fill_between(t, np.maximum(lo, floor), np.maximum(hi, floor), color=st.get("color"), alpha=0.2)
        if markers and label in markers and markers[label] is not None:
            td = markers[label]
            k = int(np.clip(np.searchsorted(t, td), 0, len(t) - 1))
            ax.plot([t[k]], [max(m[k], floor)], "x", ms=10, mew=2, color=st.get("color", "k"))
    ax.axhline(-REWARD_TARGET, color="k", ls=":", lw=1.2, label="stop rule: r = -0.1")
    ax.set_yscale("log")
    ax.set_xlabel("time t (s)")
    ax.set_ylabel("-r (log scale; lower is better)")
    ax.set_xlim(t[0], t[-1])
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title)
    return finish_figure(fig, png_path)


# ----------------------------------------------------------------------------- space-time maps
def _sym_limit(values: Sequence[np.ndarray], center: float, q: float = 99.5) -> float:
    dev = np.concatenate([np.abs(np.asarray(v, float) - center).ravel() for v in values])
    dev = dev[np.isfinite(dev)]
    lim = float(np.percentile(dev, q)) if dev.size else 0.0
    return lim if lim > 0 else max(abs(center) * 1e-3, 1e-6)


def _field_image(ax, t: np.ndarray, x: np.ndarray, f: np.ndarray, **kw):
    """``f`` (T, N) drawn with time along x and position along y, each value a cell centred on its
    (t, x). On uniform grids (the rollouts' recordings) an image: an order of magnitude cheaper to
    draw than a mesh of T x N quads at paper resolution (3 001 x 201), sampled at the nearest recorded
    value (the waves are smooth on the grid: no smoothing filter, whose gradients would triple the PNG)."""
    t, x = np.asarray(t, float), np.asarray(x, float)
    # uniform to well under a pixel (recorded times are float32: their spacing varies by ~1e-5 s)
    uniform = all(len(a) > 1 and np.allclose(np.diff(a), a[1] - a[0], rtol=1e-3, atol=0.0) for a in (t, x))
    if not uniform:
        return ax.pcolormesh(t, x, f.T, shading="nearest", rasterized=True, **kw)
    dt, dx = t[1] - t[0], x[1] - x[0]
    return ax.imshow(f.T, origin="lower", aspect="auto", interpolation="nearest",
                     extent=(t[0] - dt / 2, t[-1] + dt / 2, x[0] - dx / 2, x[-1] + dx / 2), **kw)


def plot_spacetime(
    png_path: str | Path | None, t: np.ndarray, x: np.ndarray,
    rows: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    equilibrium: tuple[float, float, float], title: str,
    diverged_at: Mapping[str, float | None] | None = None, *, fig: Figure | SubFigure | None = None,
) -> Figure | SubFigure:
    """Space-time maps of density, speed and time gap (paper figs. 4, 5, 7).

    ``rows``: label -> (rho (T, N) in veh/m, v (T, N) in m/s, h (T, N) in s); one row per
    controller, columns rho (shown in veh/km), v, h. ``equilibrium`` = (rho_bar veh/m, v_bar m/s,
    h_bar s): each column uses a diverging colour map centred there, limits shared by the column.
    ``diverged_at``: label -> time (s) after which that run was frozen (drawn as a dashed line).
    """
    rho_bar, v_bar, h_bar = equilibrium
    cols = [("density rho (veh/km)", VEH_PER_KM, rho_bar * VEH_PER_KM, colormaps["RdBu_r"].resampled(COLOUR_LEVELS)),
            ("speed v (m/s)", 1.0, v_bar, colormaps["RdBu_r"].resampled(COLOUR_LEVELS)),
            ("ACC time gap h (s)", 1.0, h_bar, colormaps["PuOr_r"].resampled(COLOUR_LEVELS))]
    n = len(rows)
    fig = new_figure(fig, figsize=(12, 2.0 * n + 1.0))
    axes = fig.subplots(n, 3, squeeze=False, sharex=True, sharey=True)
    labels = list(rows)
    for j, (cname, scale, center, cmap) in enumerate(cols):
        fields = [np.asarray(rows[lab][j], float) * scale for lab in labels]
        lim = _sym_limit(fields, center)
        norm = colors.Normalize(vmin=center - lim, vmax=center + lim)
        for i, lab in enumerate(labels):
            ax = axes[i, j]
            f = fields[i]
            mesh = _field_image(ax, t, x, f, cmap=cmap, norm=norm)
            ax.set_title(f"{lab}: {cname.split(' (')[0]}", fontsize=9)
            if np.nanmax(np.abs(f - center)) < 1e-9 * max(abs(center), 1.0):
                ax.text(0.5, 0.5, f"constant = {center:.3g} (no control action)", transform=ax.transAxes,
                        ha="center", va="center", fontsize=8, bbox=dict(fc="white", alpha=0.8))
            td = (diverged_at or {}).get(lab)
            if td is not None and np.isfinite(td):
                ax.axvline(td, color="k", ls="--", lw=1.2)
                ax.text(td, x[-1], f" diverged at {td:.0f} s; frozen after", fontsize=7, va="top",
                        ha="right" if td > 0.6 * t[-1] else "left")
        # one colour bar per column (the limits are the column's), above it
        cb = fig.colorbar(mesh, ax=axes[:, j].tolist(), location="top", extend="both", aspect=40, pad=0.01)
        cb.set_label(cname, fontsize=9)
        cb.ax.tick_params(labelsize=8)
        axes[-1, j].set_xlabel("time t (s)")
    for i in range(n):
        axes[i, 0].set_ylabel("position x (m)")
    fig.suptitle(textwrap.fill(title, 150), fontsize=12)  # a long title would widen the saved figure
    return finish_figure(fig, png_path)


# ----------------------------------------------------------------------------- L2 norms
def _l2_axes(axes, t, series, styles_dash: Mapping[str, str] | None = None) -> None:
    for i, (label, (r, v)) in enumerate(series.items()):
        st = _style(label) or dict(color=f"C{i}")
        if styles_dash and label in styles_dash:
            st["ls"] = styles_dash[label]
        for ax, y in ((axes[0], r), (axes[1], v)):
            m, lo, hi = _mean_band(np.asarray(y, float))
            ax.plot(t, np.maximum(m, 1e-12), lw=max(2.8 - 0.4 * i, 1.2), label=label, **st)
            if lo is not None and hi is not None:  # (both or neither)
                ax.fill_between(t, np.maximum(lo, 1e-12), np.maximum(hi, 1e-12), color=st.get("color"),
                                alpha=0.2)
    axes[0].set_ylabel("||rho - rho_bar||_L2 (veh/km)")
    axes[1].set_ylabel("||v - v_bar||_L2 (m/s)")
    for ax in axes:
        ax.set_yscale("log")
        ax.set_xlabel("time t (s)")
        ax.set_xlim(t[0], t[-1])
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)


def plot_l2_norms(png_path: str | Path | None, t: np.ndarray,
                  series: Mapping[str, tuple[np.ndarray, np.ndarray]], title: str, *,
                  fig: Figure | SubFigure | None = None) -> Figure | SubFigure:
    """L2 norms of the density and speed deviations over time (paper figs. 6, 8).

    ``series``: label -> (rho_L2 in veh/km, v_L2 in m/s), each (T,) or (S, T) (mean, min-max band).
    """
    fig = new_figure(fig, figsize=(12, 4.2))
    axes = fig.subplots(1, 2)
    _l2_axes(axes, t, series)
    axes[0].set_title("density deviation")
    axes[1].set_title("speed deviation")
    fig.suptitle(title)
    return finish_figure(fig, png_path)


def plot_l2_panels(png_path: str | Path | None, t: np.ndarray,
                   panels: Mapping[str, Mapping[str, tuple[np.ndarray, np.ndarray]]], title: str, *,
                   fig: Figure | SubFigure | None = None) -> Figure | SubFigure:
    """Several L2 comparisons (e.g. plant delay 3 s and 5 s, paper fig. 8): one column per panel,
    rows density and speed. ``panels``: panel title -> series as in ``plot_l2_norms``."""
    k = len(panels)
    fig = new_figure(fig, figsize=(6.2 * k, 7.5))
    axes = fig.subplots(2, k, squeeze=False)
    for j, (ptitle, series) in enumerate(panels.items()):
        _l2_axes([axes[0, j], axes[1, j]], t, series)
        axes[0, j].set_title(f"{ptitle}: density deviation")
        axes[1, j].set_title(f"{ptitle}: speed deviation")
    fig.suptitle(title)
    return finish_figure(fig, png_path)


# ----------------------------------------------------------------------------- robustness map
def plot_robustness_map(
    png_path: str | Path | None, delays: np.ndarray, alphas: np.ndarray,
    maps: Mapping[str, tuple[np.ndarray, np.ndarray]], title: str,
    nominal: tuple[float, float] | None = (4.0, 0.15), initial_l2: float | None = None,
    quantity: str = "final ||rho - rho_bar||_L2 (veh/km)", stable_below: float | None = None, *,
    fig: Figure | SubFigure | None = None,
) -> Figure | SubFigure:
    """Heatmaps of a final density deviation (veh/km, on a log colour scale) over plant delay (rows of the
    arrays, s) x plant ACC rate alpha (columns), one panel per controller.

    ``maps``: label -> (value (ND, NA) in veh/km, diverged (ND, NA) bool). Diverged cells are
    drawn grey with hatching. ``nominal`` marks the training point (D, alpha) with a red star;
    ``initial_l2`` (veh/km), if given, is marked on the colour bar. ``quantity`` labels the bar.
    ``stable_below`` (veh/km): also count, in each panel's title, the cells below it that did not diverge.
    """
    delays, alphas = np.asarray(delays, float), np.asarray(alphas, float)
    k = len(maps)
    ncol = min(k, 2)
    nrow = math.ceil(k / ncol)
    vals = [np.asarray(m[0], float) for m in maps.values()]
    good = np.concatenate([v[~np.asarray(m[1], bool) & np.isfinite(v)].ravel()
                           for v, m in zip(vals, maps.values(), strict=True)])
    vmin = max(float(np.min(good)) if good.size else 1e-3, 1e-4)
    vmax = max(float(np.max(good)) if good.size else 1.0, vmin * 10)
    norm = colors.LogNorm(vmin=vmin, vmax=vmax)

    def edges(c):
        if c.size == 1:
            return np.array([c[0] - 0.5, c[0] + 0.5])
        mid = 0.5 * (c[1:] + c[:-1])
        return np.concatenate([[c[0] - (mid[0] - c[0])], mid, [c[-1] + (c[-1] - mid[-1])]])

    ae, de = edges(alphas), edges(delays)
    fig = new_figure(fig, figsize=(6.4 * ncol, 4.6 * nrow))
    axes = fig.subplots(nrow, ncol, squeeze=False)
    mesh = None
    for ax, (label, (_, div)), v in zip(axes.flat, maps.items(), vals, strict=False):
        div = np.asarray(div, bool) | ~np.isfinite(v)
        mesh = ax.pcolormesh(ae, de, np.ma.masked_where(div, v), cmap="viridis", norm=norm)
        if div.any():
            ax.pcolor(ae, de, np.ma.masked_where(~div, np.ones_like(v)), cmap=colors.ListedColormap(["0.75"]),
                      hatch="xx", edgecolor="0.4", lw=0)
        if nominal is not None:
            ax.plot([nominal[1]], [nominal[0]], marker="*", ms=14, color="red", mec="white", ls="none")
        nd = int(div.sum())
        stable = "" if stable_below is None else f"{int((~div & (v < stable_below)).sum())} stabilised, "
        ax.set_title(f"{label}  ({stable}{nd}/{div.size} diverged)", fontsize=10)
        ax.set_xlabel("plant ACC penetration rate alpha")
        ax.set_ylabel("plant input delay D (s)")
    for ax in list(axes.flat)[k:]:
        ax.remove()
    if nominal is not None:
        title = (f"{title}\nred star: nominal point (D = {nominal[0]:g} s, alpha = {nominal[1]:g}), the training point "
                 "of the laws trained at one plant")
    if mesh is not None:
        cb = fig.colorbar(mesh, ax=axes.ravel().tolist()[:k], shrink=0.8, extend="both")
        cb.set_label(f"{quantity}, log scale; grey hatched = diverged")
        cb.ax.yaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        cb.ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda val, _: f"{val:g}"))
        cb.ax.yaxis.set_minor_formatter(ticker.NullFormatter())
        if initial_l2 is not None and vmin <= initial_l2 <= vmax:
            cb.ax.axhline(initial_l2, color="red", lw=2)
            cb.ax.text(1.05, initial_l2, " initial", color="red", fontsize=7,
                       transform=cb.ax.get_yaxis_transform(), va="center")
    fig.suptitle(title)
    return finish_figure(fig, png_path)
