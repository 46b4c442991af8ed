"""Every figure of the evaluation, from the scenario outcomes (``paper.plotting`` draws them)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from jaxtraffic.model.params import equilibrium
from jaxtraffic.paper import laws
from jaxtraffic.paper.learned import STABLE_STD
from jaxtraffic.paper.maps import four_rows, map_table
from jaxtraffic.paper.oracle import ORACLE_LABELS
from jaxtraffic.paper.scenarios import (
    CTRL_DELAY,
    NOISE_STD,
    SCENARIO_BY_NAME,
    EvalConfig,
    Outcome,
    initial_norms,
    learned,
)

# ----------------------------------------------------------------------------- figures
FIG7 = ("fig7_spacetime_alpha_noise.png", "fig7_l2_alpha_noise.png")  # drawn from the reading the claims choose
ROBUSTNESS = ("robustness_map.png", "robustness_map_waves.png", "robustness_map_told.png")
LEARNING_CURVE = "fig3a_learning_curve.png"


def make_figures(results: dict[str, dict[str, Outcome]], robust: dict[str, dict[str, np.ndarray]],
                 eval_config: EvalConfig, out_dir: Path, learning_curve_csv: Path | None,
                 log: Callable[[str], None] = print, fig7_scenario: str = "alpha_noise",
                 select: Callable[[str], bool] | None = None, oracle: dict[str, dict] | None = None,
                 table: dict[str, Any] | None = None) -> list[str]:
    """Write every figure into ``out_dir``; returns the file names written. ``fig7_scenario``: the
    reading of the alpha noise shown as figure 7 (``claims.paper_like_reading``). ``select``: draw only
    the figures whose file name it accepts (default: all), e.g. the scenario figures while the
    robustness map is still running (``FIG7`` and ``ROBUSTNESS`` need later results). ``oracle``: oracle rows
    (``paper.oracle``) drawn as further panels of the waves map. ``table``: the map's counts by what each
    controller is told (``maps.map_table``; default: computed here), for the four controllers side by side."""
    canvas = _Canvas(out_dir, select or (lambda name: True), log)
    labels = {c: laws.short_label(c) for c in {*laws.LAWS, *results["delay4"]}}  # a name not registered: itself
    _learning_curve_figure(canvas, learning_curve_csv)
    t = results["delay4"]["open_loop"].t
    _reward_figure(canvas, results, t, labels)
    _spacetime_figures(canvas, results, eval_config, t, labels, fig7_scenario)
    _l2_figures(canvas, results, eval_config, t, labels, fig7_scenario)
    if robust and any(canvas.want(name) for name in ROBUSTNESS):
        _robustness_figures(canvas, robust, eval_config, labels, oracle)
        _told_figure(canvas, robust, eval_config, table or map_table(robust, {}, eval_config))
    return canvas.written


@dataclass
class _Canvas:
    """Where the figures go: ``draw`` writes those ``want`` accepts, their names kept in ``written`` in order."""

    out_dir: Path
    want: Callable[[str], bool]
    log: Callable[[str], None]
    written: list[str] = field(default_factory=list)

    def draw(self, name: str, plot: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """``plot(out_dir / name, *args, **kwargs)`` if ``want(name)``, logged."""
        if self.want(name):
            plot(self.out_dir / name, *args, **kwargs)
            self.written.append(name)
            self.log(f"  wrote {name}")


def _learning_curve_figure(canvas: _Canvas, learning_curve_csv: Path | None) -> None:
    """Figure 3a from the run's learning_curve.csv; skipped (and logged) without one or if it is unreadable."""
    from jaxtraffic.paper.plotting import plot_learning_curve

    if canvas.want(LEARNING_CURVE) and learning_curve_csv is not None and Path(learning_curve_csv).exists():
        try:
            canvas.draw(LEARNING_CURVE, lambda path: plot_learning_curve(
                learning_curve_csv, path, title="PPO learning curve, D = 4 s (paper fig. 3a)"))
        except ValueError as e:
            canvas.log(f"  learning curve not plotted: {e}")
    elif canvas.want(LEARNING_CURVE):
        canvas.log("  no learning_curve.csv: fig3a skipped")


def _reward_figure(canvas: _Canvas, results: dict[str, dict[str, Outcome]], t: np.ndarray,
                   labels: dict[str, str]) -> None:
    """Figure 3b: the first seed's reward over time; the baselines and PPO at D = 4 s, Lyapunov and PPO at D = 0.

    Args:
        t: (T,) recording times, s. labels: controller name -> its label in the legends.
    """
    from jaxtraffic.paper.plotting import plot_reward

    series, markers = {}, {}
    for scenario, delay, controllers in (("delay4", "D = 4 s", ("open_loop", "lyapunov", "backstepping", "ppo")),
                                         ("delay0", "D = 0", ("lyapunov", "ppo"))):
        for c in controllers:
            o = results[scenario][c]
            key = f"{labels[c]} ({delay})"
            series[key] = o.reward[0]
            if o.metrics["diverged"][0]:
                markers[key] = float(o.metrics["diverged_at_s"][0])
    canvas.draw("fig3b_reward.png", plot_reward, t, series, markers=markers,
                title="Reward over time from the paper's initial condition (paper fig. 3b)")


def _spacetime_figures(canvas: _Canvas, results: dict[str, dict[str, Outcome]], eval_config: EvalConfig, t: np.ndarray,
                       labels: dict[str, str], fig7_scenario: str) -> None:
    """Figures 4, 5 and 7 and the mismatched delays' space-time plots: rho, v and h of the first seed.

    Args:
        t: (T,) recording times, s. labels: controller name -> its label.
        fig7_scenario: the alpha noise reading drawn as figure 7.
    """
    from jaxtraffic.paper.plotting import plot_spacetime

    nom = eval_config.nominal()
    rho_bar, v_bar = (float(x) for x in equilibrium(nom))
    eq = (rho_bar, v_bar, float(nom.h_bar))
    x = np.asarray(nom.x())
    titles = {
        "delay0": ("fig4_spacetime_delay0.png", "Plant delay D = 0 (paper fig. 4)"),
        "delay4": ("fig5_spacetime_delay4.png", "Plant delay D = 4 s (paper fig. 5)"),
        fig7_scenario: (FIG7[0],
                        f"D = 4 s, plant alpha = 0.15 + N(0, {NOISE_STD}^2), reading {fig7_scenario}: "
                        f"{SCENARIO_BY_NAME[fig7_scenario].description}; seed {eval_config.seeds[0]} (paper fig. 7)"),
        "delay_mismatch_3": ("spacetime_delay_mismatch_3.png", "Plant delay 3 s, controllers assume 4 s"),
        "delay_mismatch_5": ("spacetime_delay_mismatch_5.png", "Plant delay 5 s, controllers assume 4 s"),
    }
    for scenario, (fname, title) in titles.items():
        if not canvas.want(fname):
            continue
        rows, div = {}, {}
        for c, o in results[scenario].items():
            rows[labels[c]] = (o.rho[0], o.v[0], o.h[0])
            if o.metrics["diverged"][0]:
                div[labels[c]] = float(o.metrics["diverged_at_s"][0])
        canvas.draw(fname, plot_spacetime, t, x, rows, eq, title, diverged_at=div)


def _l2_figures(canvas: _Canvas, results: dict[str, dict[str, Outcome]], eval_config: EvalConfig, t: np.ndarray,
                labels: dict[str, str], fig7_scenario: str) -> None:
    """Figures 4, 6, 7 and 8's L2 norms of the deviations (mean and min-max band over the seeds).

    Args:
        t: (T,) recording times, s. labels: controller name -> its label.
        fig7_scenario: the alpha noise reading drawn as figure 7.
    """
    from jaxtraffic.paper.plotting import plot_l2_norms, plot_l2_panels

    def l2(scenario, ctrls):  # the extra learned controllers are added where they were evaluated
        ctrls = (*ctrls, *(c for c in learned(results[scenario]) if c not in ctrls))
        return {labels[c]: (results[scenario][c].rho_L2, results[scenario][c].v_L2) for c in ctrls}

    canvas.draw("fig4_l2_delay0.png", plot_l2_norms, t, l2("delay0", ("open_loop", "lyapunov", "ppo")),
                "L2 norms of the deviations, plant delay D = 0")
    canvas.draw("fig6_l2_delay4.png", plot_l2_norms, t,
                l2("delay4", ("open_loop", "lyapunov", "backstepping", "ppo")),
                "L2 norms of the deviations, plant delay D = 4 s (paper fig. 6)")
    canvas.draw(FIG7[1], plot_l2_norms, t, l2(fig7_scenario, ("backstepping", "ppo")),
                f"L2 norms with alpha noise (D = 4 s, reading {fig7_scenario}): mean and min-max band "
                f"over {len(eval_config.seeds)} seeds")
    canvas.draw("fig8_l2_delay_mismatch.png", plot_l2_panels, t,
                {"plant D = 3 s": l2("delay_mismatch_3", ("backstepping", "ppo")),
                 "plant D = 5 s": l2("delay_mismatch_5", ("backstepping", "ppo"))},
                "Mismatched delay, controllers assume 4 s (paper fig. 8)")


def _robustness_figures(canvas: _Canvas, robust: dict[str, dict[str, np.ndarray]], eval_config: EvalConfig,
                        labels: dict[str, str], oracle: dict[str, dict] | None) -> None:
    """The robustness maps over plant delay x plant alpha: final density L2 deviation, remaining waves.

    The waves map (spatial std of rho) has the oracle's rows as further panels.

    Args:
        robust: controller -> quantity -> (n_delays, n_alphas) array (``scenarios.run_robustness``).
        labels: controller name -> its label. oracle: oracle rows (``paper.oracle``), or None.
    """
    from jaxtraffic.paper.plotting import plot_robustness_map

    names = {**{c: laws.label(c) for c in robust}, "backstepping": "backstepping (assumes the true plant delay)",
             "ppo": "PPO (trained D = 4 s)", **{c: labels.get(c, c) for c in learned(robust) if c != "ppo"}}
    delays, alphas = np.asarray(eval_config.robust_delays), np.asarray(eval_config.robust_alphas)
    horizon = replace(eval_config, horizon_s=eval_config.robust_horizon_s).n_steps * eval_config.dt
    maps = {names[c]: (r["final_rho_L2"], r["diverged"]) for c, r in robust.items()}
    canvas.draw(ROBUSTNESS[0], plot_robustness_map, delays, alphas, maps,
                f"Final density L2 deviation from the nominal target after {horizon:g} s, over plant delay x "
                "plant ACC rate\n(includes the steady offset a proportional law keeps when alpha != 0.15)",
                nominal=(CTRL_DELAY, 0.15), initial_l2=initial_norms(eval_config)[0])
    maps = {names[c]: (r["final_rho_spatial_std"], r["diverged"]) for c, r in robust.items()}
    maps.update({ORACLE_LABELS[k]: (r["final_rho_spatial_std"], r["diverged"]) for k, r in (oracle or {}).items()})
    canvas.draw(ROBUSTNESS[1], plot_robustness_map, delays, alphas, maps,
                f"Remaining density waves after {horizon:g} s: spatial standard deviation of rho "
                "(blind to a uniform offset)", nominal=(CTRL_DELAY, 0.15), initial_l2=initial_norms(eval_config)[0],
                quantity="final std_x(rho) (veh/km)", stable_below=STABLE_STD)


def _told_figure(canvas: _Canvas, robust: dict[str, dict[str, np.ndarray]], eval_config: EvalConfig,
                 table: dict[str, Any]) -> None:
    """The remaining waves of the four controllers side by side (``maps.four_rows``: backstepping, adaptive
    backstepping, the best learned law, backstepping told alpha), each labelled with what it is told."""
    from jaxtraffic.paper.plotting import plot_robustness_map

    rows = four_rows(table)
    if not rows:
        return
    delays, alphas = np.asarray(eval_config.robust_delays), np.asarray(eval_config.robust_alphas)
    horizon = replace(eval_config, horizon_s=eval_config.robust_horizon_s).n_steps * eval_config.dt
    maps = {f"{laws.label(c)},\ntold {table['rows'][c]['told']}":
            (robust[c]["final_rho_spatial_std"], robust[c]["diverged"]) for c in rows}
    canvas.draw(ROBUSTNESS[2], plot_robustness_map, delays, alphas, maps,
                f"Remaining density waves after {horizon:g} s by what each controller is told "
                f"({len(table['excluded'])} cells inconsistent before any control acts: diverged for all)",
                nominal=(CTRL_DELAY, 0.15), initial_l2=initial_norms(eval_config)[0],
                quantity="final std_x(rho) (veh/km)", stable_below=STABLE_STD)
