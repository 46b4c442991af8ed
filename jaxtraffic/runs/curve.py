"""The learning curve of a training run: learning_curve.csv (written atomically) and its figure
(paper fig. 3a). The paper's figures (``paper.plotting``) share ``new_figure``, ``finish_figure`` and
``reward_axis``.

Figures are drawn on ``matplotlib.figure.Figure`` objects, never through pyplot: no backend is
chosen and nothing global changes, so the plotting functions work the same in a script, under the
command lines and in a notebook (where the returned figure displays itself).
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import numpy as np
from matplotlib import ticker
from matplotlib.axes import Axes
from matplotlib.figure import Figure, SubFigure

from jaxtraffic.io.drawing import finish_figure, new_figure
from jaxtraffic.io.files import atomic_write_text, read_text
from jaxtraffic.sim.metrics import REWARD_TARGET

CURVE_FIELDS = ["update", "env_steps", "wall_s", "mean_reward", "eval_reward", "eval_reward_min",
                "eval_reward_max", "eval_J_comfort", "eval_rho_L2_veh_km", "eval_wave_speed", "val_score",
                "best_val_score", "eta1", "eta2", "eta3", "entropy", "approx_kl", "value_loss", "restarts"]
# columns renamed since: old name -> new name (rows of a resumed older run, older CSV files)
RENAMED_FIELDS = {"eval_rho_L2": "eval_rho_L2_veh_km"}
CURVE_LIMIT = 2**28  # bytes: a learning curve has one short row per update


def write_curve(path: Path, rows: list[dict], fields: list[str] = CURVE_FIELDS) -> None:
    """learning_curve.csv with the columns ``fields`` (default: PPO's ``CURVE_FIELDS``; atomic write)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore")
    w.writeheader()
    w.writerows({RENAMED_FIELDS.get(k, k): v for k, v in r.items()} for r in rows)
    atomic_write_text(path, buf.getvalue())


def append_curve(path: Path, row: dict, fields: list[str] = CURVE_FIELDS) -> None:
    """Append one row to learning_curve.csv (whose header ``write_curve`` wrote), flushed and fsynced.
    The trainer appends a row per chunk (the checkpoint is written every ``checkpoint_every`` chunks,
    so the file may run ahead of it); on resume it rewrites the file once from the checkpoint's rows,
    so a resumed run's CSV matches its checkpoint."""
    buf = io.StringIO()
    csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore").writerow(row)
    try:  # (not through a symbolic link: write_curve made the file; a link put there since is refused)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_NOFOLLOW)
    except OSError as err:
        raise ValueError(f"{path}: cannot append to it ({err.strerror})") from None
    with os.fdopen(fd, "a", newline="") as f:
        f.write(buf.getvalue())
        f.flush()
        os.fsync(f.fileno())


def read_learning_curve(csv_path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a learning_curve.csv as float arrays (empty cells become NaN; renamed columns of
    older files under their current names, ``RENAMED_FIELDS``)."""
    rows = list(csv.DictReader(io.StringIO(read_text(csv_path, CURVE_LIMIT), newline="")))
    if not rows:
        raise ValueError(f"{csv_path}: no rows")
    out = {}
    for key in rows[0]:
        vals = []
        for r in rows:
            try:
                vals.append(float(r[key]))
            except (TypeError, ValueError):
                vals.append(math.nan)
        out[RENAMED_FIELDS.get(key, key)] = np.asarray(vals)
    return out


def reward_axis(ax: Axes, values: np.ndarray) -> None:
    """Linear y axis, or symlog when the rewards span decades below the stop rule."""
    finite = values[np.isfinite(values)]
    if finite.size and np.min(finite) < 20 * REWARD_TARGET:
        ax.set_yscale("symlog", linthresh=0.01)
    ax.axhline(REWARD_TARGET, color="k", ls="--", lw=1, label="stop rule r = -0.1")
    ax.grid(alpha=0.3, which="both")


def plot_learning_curve(csv_path: str | Path, png_path: str | Path | None = None, title: str | None = None, *,
                        fig: Figure | SubFigure | None = None) -> Figure | SubFigure:
    """Paper fig. 3a: training reward against environment steps and against wall-clock seconds; returns
    the figure (drawn into ``fig`` if given), saved at ``png_path`` if given (in the format its suffix names).

    Reads ``csv_path`` (header ``update,env_steps,wall_s,mean_reward,eval_reward,...``) and plots
    the mean training reward and the deterministic evaluation reward (of the best member, in a
    population: ``eval_reward_max``; ``eval_reward`` is the members' mean), with the -0.1 stop-rule line
    and a dotted line where a random restart re-initialised a member.
    """
    data = read_learning_curve(csv_path)
    ev_key, ev_label = "eval_reward", "evaluation reward (deterministic policy)"
    if "eval_reward_max" in data and not np.allclose(data["eval_reward_max"], data["eval_reward"], equal_nan=True):
        ev_key, ev_label = "eval_reward_max", "evaluation reward, best member (deterministic policy)"  # a population
    series = [(k, lab) for k, lab in (("mean_reward", "mean training reward (stochastic policy)"), (ev_key, ev_label))
              if k in data and np.isfinite(data[k]).any()]
    if not series:
        raise ValueError(f"{csv_path}: no mean_reward / eval_reward values")
    xaxes = [(k, lab) for k, lab in (("env_steps", "environment steps"), ("wall_s", "wall-clock time (s)"))
             if k in data and np.isfinite(data[k]).any()]
    if not xaxes:
        xaxes = [("update", "PPO update")]
    fig = new_figure(fig, figsize=(6.2 * len(xaxes), 4.2))
    axes = fig.subplots(1, len(xaxes), squeeze=False)
    allv = np.concatenate([data[k] for k, _ in series])
    for ax, (xk, xlab) in zip(axes[0], xaxes, strict=True):
        for (yk, ylab), col in zip(series, ("tab:green", "tab:purple"), strict=False):
            ok = np.isfinite(data[xk]) & np.isfinite(data[yk])
            ax.plot(data[xk][ok], data[yk][ok], color=col, lw=1.5, marker="." if ok.sum() < 60 else None,
                    label=ylab)
        reward_axis(ax, allv)
        if "restarts" in data:  # a member re-initialised after the row before (runs.ppo.trainer random restarts)
            count = np.nan_to_num(data["restarts"])
            for i, x in enumerate(data[xk][1:][np.diff(count) > 0]):
                ax.axvline(x, color="0.5", ls=":", lw=1, label="random restart" if i == 0 else None)
        if xk == "env_steps":
            ax.xaxis.set_major_formatter(ticker.EngFormatter(sep=""))
        ax.set_xlabel(xlab)
        ax.set_ylabel("reward r (dimensionless)")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=9)
    fig.suptitle(title or "PPO learning curve (paper fig. 3a)")
    return finish_figure(fig, png_path)


