"""The stability certificate of the learned controllers (``control.stability``): figure and REPORT section.

``certificate_section`` reads each learned run's certificate (its summary.json: the gains it settles to at the
equilibrium, certified at its training delay and alpha with its filter width) and draws
``fig_certificate.png``: the growth rate over wavelength of each learned law, with and without its filter,
and the stable region in (eta2, eta3) at D = 4 s, alpha = 0.15 (at eta1 = 0) of the filtered law (wavelengths
5-2000 m), the learned gains marked.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.gain_law import FILTER_SIGMA
from jaxtraffic.control.stability import GROWTH_TOL, growth_rates, stable_region, verdict, wavenumbers
from jaxtraffic.io.drawing import new_figure, save_figure
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.paper import laws

ETA2 = np.linspace(-3.0, 1.0, 17)
ETA3 = np.linspace(-4.0, 1.0, 17)
REGION_K = 2 * np.pi / np.geomspace(2000.0, 5.0, 48)  # the band where delayed gain laws go unstable


def _certificates(learned_runs: dict[str, dict]) -> dict[str, dict]:
    return {k: r["summary"]["certificate"] for k, r in learned_runs.items()
            if r.get("summary", {}).get("certificate")}


def plot_certificate(png: Path, certs: dict[str, dict], delay: float = 4.0) -> None:
    p = TrafficParams(alpha=0.15)
    k = wavenumbers(float(p.L))
    wl = 2 * np.pi / k
    fig = new_figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2)
    ax = axes[0]
    for i, (name, c) in enumerate(certs.items()):
        color = f"C{i}"
        for sigma, ls in ((c["sigma"], "-"), (0.0, ":")):
            s = np.asarray(growth_rates(c["gains"], p.replace(alpha=c["alpha"]), c["delay"], jnp.asarray(k), sigma))
            ax.plot(wl, s, ls, color=color, label=f"{laws.label(name)}, sigma {sigma:g} m")
    ax.axhline(GROWTH_TOL, color="k", lw=0.8, ls="--", label="tolerance")
    ax.set_xscale("log")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_xlabel("wavelength (m)")
    ax.set_ylabel("growth rate (1/s)")
    ax.set_title("linearised closed loop, every wavenumber")
    ax.legend(fontsize=6)
    ax.grid(alpha=0.3)
    for ax, sigma in ((axes[1], FILTER_SIGMA),):
        region = stable_region(p, delay, 0.0, ETA2, ETA3, sigma, k=REGION_K)
        im = ax.pcolormesh(ETA3, ETA2, np.clip(region, -0.02, 0.1), cmap="RdBu_r", vmin=-0.1, vmax=0.1,
                           shading="auto")
        ax.contour(ETA3, ETA2, region, levels=[GROWTH_TOL], colors="k", linewidths=1.2)
        for i, (name, c) in enumerate(certs.items()):
            ax.plot(c["gains"][2], c["gains"][1], "o", color=f"C{i}", mec="k",
                    label=f"{laws.label(name)} (eta1 {c['gains'][0]:+.2f})")
        ax.set_xlabel("eta3 (density gain)")
        ax.set_ylabel("eta2 (speed gain)")
        ax.set_title(f"max growth, D = {delay:g} s, alpha 0.15, eta1 = 0, sigma {sigma:g} m\n(black: {GROWTH_TOL:g}/s)")
        fig.colorbar(im, ax=ax, label="1/s")
    axes[1].legend(fontsize=6, loc="lower left")
    save_figure(fig, png)


def certificate_section(learned_runs: dict[str, dict], out_dir: str | Path,
                        log: Callable[[str], None] = print) -> list[str]:
    """REPORT.md lines: each learned run's certificate, and ``fig_certificate.png`` in ``out_dir`` (a law the
    certificate does not model, e.g. the residual on adaptive backstepping, is listed with the reason)."""
    every = _certificates(learned_runs)
    certs = {k: c for k, c in every.items() if c.get("applies", True)}
    if not every:
        return []
    if not certs:
        return ["## Stability certificate of the learned laws", "", *_not_applicable(every), ""]
    plot_certificate(Path(out_dir) / "fig_certificate.png", certs)
    log("  wrote fig_certificate.png")
    lines = ["## Stability certificate of the learned laws", "",
             "The linearised closed loop of the three-gain law with input delay, continuous in x, every wavenumber "
             "(docs/model.md section 16), at the gains each learned controller settles to at the equilibrium, its "
             "training delay and alpha, with its filter. Certified: largest growth rate <= 0 (no mode grows); "
             f"marginal: it grows, slower than {GROWTH_TOL:g}/s (an e-fold in over 1000 s; the training's check "
             "lets it pass); not certified: faster.", "",
             "| controller | gains at equilibrium (eta1, eta2, eta3) | D (s) | alpha | filter sigma (m) "
             "| max growth (1/s) | at wavelength (m) | verdict |", "|---|---|---|---|---|---|---|---|"]
    for name, c in certs.items():
        lines.append(f"| {laws.label(name)} | ({', '.join(f'{g:+.3f}' for g in c['gains'])}) | "
                     f"{c['delay']:g} | {c['alpha']:g} | {c['sigma']:g} | {c['max_growth']:+.2e} | "
                     f"{c['worst_wavelength']:.3g} | **{verdict(c['max_growth'])}** |")
    lines += ["", *_not_applicable(every), "", "![certificate](fig_certificate.png)", ""]
    return lines


def _not_applicable(certs: dict[str, dict]) -> list[str]:
    """One line per learned law the certificate does not model (its summary says ``"applies": false``), and why."""
    return [f"- {laws.label(name)}: no certificate: {c.get('reason', 'it does not apply')}."
            for name, c in certs.items() if not c.get("applies", True)]
