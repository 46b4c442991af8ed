"""``evaluate_all``: every scenario, the robustness map, figures, tables, metrics.json, claims.json, REPORT.md."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax

from jaxtraffic.control import Controller
from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.io.files import as_lists, atomic_write_text, to_jsonable, write_json
from jaxtraffic.io.provenance import provenance
from jaxtraffic.model.params import equilibrium
from jaxtraffic.paper import laws
from jaxtraffic.paper.claims import evaluate_claims, paper_like_reading
from jaxtraffic.paper.figures import FIG7, ROBUSTNESS, make_figures
from jaxtraffic.paper.learned import comparison_section
from jaxtraffic.paper.maps import map_controllers, map_table
from jaxtraffic.paper.numerics import deploy, relative_to, run_numerics
from jaxtraffic.paper.report import numerics_summary, readings_summary, report_text, robustness_summary
from jaxtraffic.paper.scenarios import (
    CTRL_DELAY,
    SCENARIOS,
    EvalConfig,
    Outcome,
    initial_norms,
    run_robustness,
    run_scenarios,
    told,
)
from jaxtraffic.paper.summaries import UNITS, equilibrium_indices, summarise
from jaxtraffic.paper.table2 import table2_rows, write_table2
from jaxtraffic.platform import distributed
from jaxtraffic.sim.metrics import LATE_WINDOW_S, VEH_PER_KM


# ----------------------------------------------------------------------------- driver
class _Background:
    """``fn(*args, log=..., **kwargs)`` in a thread, its log lines kept for ``join``.

    Used for the scenario figures (matplotlib draws while XLA runs the robustness map, which
    releases the GIL while it computes; only this thread uses matplotlib until ``join``) and for
    the numerics check (its programs compile and run alongside the robustness map's, on the
    core those leave free: compilation uses about one core and a small batch does not fill two).

    In a multi-process run ``fn`` runs at once, in the caller's thread: the batched rollouts are
    SPMD programs that every process must launch in the same order."""

    def __init__(self, fn: Callable[..., Any], *args, name: str = "figures", **kwargs):
        self.lines: list[str] = []
        self.result: Any = None
        self.error: BaseException | None = None
        if jax.process_count() > 1:
            self.thread = None
            self.result = fn(*args, log=self.lines.append, **kwargs)
            return

        def run() -> None:
            try:
                self.result = fn(*args, log=self.lines.append, **kwargs)
            except BaseException as exc:  # re-raised in the caller's thread by join
                self.error = exc

        self.thread = threading.Thread(target=run, name=f"jaxtraffic-{name}", daemon=True)
        self.thread.start()

    def join(self, log: Callable[[str], None]) -> Any:
        if self.thread is not None:
            self.thread.join()
        for line in self.lines:
            log(line)
        if self.error is not None:
            raise self.error
        return self.result


def evaluate_all(controllers: dict[str, Controller], eval_config: EvalConfig, out_dir: str | Path,
                 meta: dict[str, Any], **options: Any) -> dict[str, Any]:
    """``evaluate_plant``, then its REPORT.md written into ``out_dir``; return the metrics dict."""
    metrics, report = evaluate_plant(controllers, eval_config, out_dir, meta, **options)
    if distributed.is_writer():
        atomic_write_text(Path(out_dir) / "REPORT.md", report)
    return metrics


def evaluate_plant(controllers: dict[str, Controller], eval_config: EvalConfig, out_dir: str | Path,
                   meta: dict[str, Any], ppo_delay0: Controller | None = None,
                   learning_curve_csv: str | Path | None = None, log: Callable[[str], None] = print,
                   learned_runs: dict[str, dict] | None = None, grids: dict[str, ControllerGrid] | None = None,
                   oracle: dict[str, dict] | None = None) -> tuple[dict[str, Any], str]:
    """Run every scenario and the robustness map, write every output but REPORT.md; return the metrics dict
    and REPORT.md's text (``paper.job`` adds the sections that compare plants and certify the learned laws).

    ``controllers`` must hold "ppo" (the D = 4 s policy); the baselines are added if missing.
    ``ppo_delay0``: a separate policy for scenario delay0 (else the D = 4 s one is used).
    ``learned_runs``: controller name -> {"summary", "curve", "run_dir"} of the runs behind the
    learned controllers, for REPORT.md's comparison section (``paper.learned``).
    ``grids``: the grid each learned controller acts on (``runs.policy.policy_grid``; "ppo" also for
    ``ppo_delay0``); every controller is adapted from its grid to the evaluation plant (``numerics.deploy``).
    With ``eval_config.numerics_check`` Table 2's scenario is rerun on a refined plant and with the other scheme.
    ``oracle``: the map's oracle rows (``paper.oracle.load_oracle``), drawn and tabulated beside the controllers.

    In a multi-process run (``jaxtraffic.platform.distributed``) every process must call it with the same
    arguments: the batched rollouts are split over every process's devices, every process gets
    the metrics, and only process 0 draws and writes.
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    writer = distributed.is_writer()
    if writer:
        out_dir.mkdir(parents=True, exist_ok=True)
    ctrls = laws.build_model_based("all")  # the registry's model-based laws (paper.laws)
    ctrls.update(controllers)
    grids = grids or {}
    # independent of the rest: its programs compile and run alongside the scenarios' and the map's
    checking = _Background(run_numerics, ctrls, grids, eval_config,
                           name="numerics") if eval_config.numerics_check else None
    if ppo_delay0 is not None:
        ppo_delay0 = deploy({"ppo": ppo_delay0}, grids, eval_config)["ppo"]
    ctrls = deploy(ctrls, grids, eval_config)
    lc = Path(learning_curve_csv) if learning_curve_csv else None
    results, early = _scenarios(ctrls, ppo_delay0, eval_config, out_dir, lc, writer, checking is not None, log)
    init_l2 = initial_norms(eval_config)
    metrics: dict[str, Any] = {"units": UNITS}
    for s, per in results.items():
        metrics[s] = {c: summarise(o, init_l2) for c, o in per.items()}
    log(f"[2/4] robustness map: {len(eval_config.robust_delays)} delays x {len(eval_config.robust_alphas)} alphas, "
        f"{eval_config.robust_horizon_s:g} s"
        + ("" if eval_config.robust_delays and eval_config.robust_alphas else " (skipped)"))
    map_ctrls = {**ctrls, **deploy(map_controllers(), {}, eval_config)}  # + the map-only model-based rows
    robust = run_robustness(map_ctrls, eval_config, log)
    table = map_table(robust, {n: told(n, c) for n, c in map_ctrls.items()}, eval_config) if robust else None
    numerics = None
    if checking is not None:
        log("  numerical check of Table 2 (delay4): refined grid and the other scheme")
        numerics = relative_to(checking.join(log), metrics["delay4"])
        metrics["numerics"] = numerics

    lc_data = _read_learning_curve(lc)
    d0_label = "a separate D = 0 policy" if ppo_delay0 is not None else "the D = 4 s policy"
    claims = evaluate_claims(metrics, eval_config, lc_data, d0_label)
    fig7 = paper_like_reading(claims)
    figures: list = []
    if writer:
        log("[3/4] figures")
        assert early is not None  # (made where this process draws)
        figures = early.join(log)  # the scenario figures, drawn while the robustness map ran
        figures += make_figures(results, robust, eval_config, out_dir, lc, log, fig7_scenario=fig7,
                                select=lambda name: name in FIG7 + ROBUSTNESS, oracle=oracle, table=table)
        log("[4/4] tables, metrics.json, REPORT.md")
        write_table2(table2_rows(metrics, eval_config, numerics), out_dir, eval_config.n_steps * eval_config.dt,
                     metrics, numerics)
    meta = _meta(meta, eval_config, grids, fig7, init_l2)
    meta["runtime_s"] = time.perf_counter() - t_start
    meta["claims"] = {str(c["id"]): c["verdict"] for c in claims}
    meta["claim5_readings"] = {n: r["verdict"] for c in claims if c["id"] == 5 for n, r in c["readings"].items()}
    metrics["meta"] = meta
    metrics = to_jsonable(metrics)
    report = ""
    if writer:
        report = _write(out_dir, claims, metrics, meta, figures, robust, _robustness_json(robust, eval_config, table),
                        eval_config, numerics, lc_data, learned_runs, oracle, table)
    log(f"done in {meta['runtime_s']:.1f} s -> {out_dir}")
    return metrics, report


def _scenarios(ctrls: dict[str, Controller], ppo_delay0: Controller | None, eval_config: EvalConfig, out_dir: Path,
               learning_curve_csv: Path | None, writer: bool, checking: bool,
               log: Callable[[str], None]) -> tuple[dict[str, dict[str, Outcome]], _Background | None]:
    """Step 1: every scenario with every controller; on the writer, their figures started in the background.

    The figures that need the claims or the robustness map (``FIG7``, ``ROBUSTNESS``) are left for later.

    Args:
        ctrls: controller name -> controller, deployed on ``eval_config``'s plant. ppo_delay0: the policy for
            scenario delay0 in place of "ppo", or None. writer: whether this process draws.
        checking: whether the numerical check runs alongside (for the log line).

    Returns:
        The outcomes (scenario -> controller -> ``Outcome``) and the figures' ``_Background`` (None
        where this process does not draw).
    """
    overrides = {("delay0", "ppo"): ppo_delay0} if ppo_delay0 is not None else {}
    log(f"[1/4] scenarios: {eval_config.describe()}, {eval_config.horizon_s:g} s "
        f"({eval_config.n_steps} steps), {len(eval_config.seeds)} noise seeds"
        + ("; the numerical check of Table 2 runs alongside" if checking else ""))
    results = run_scenarios(ctrls, eval_config, log, overrides)
    early = _Background(make_figures, results, {}, eval_config, out_dir, learning_curve_csv,
                        select=lambda name: name not in FIG7 + ROBUSTNESS) if writer else None
    return results, early


def _read_learning_curve(path: Path | None) -> dict[str, Any] | None:
    """The columns of learning_curve.csv (``plotting.read_learning_curve``); None if absent or unreadable."""
    if path is None or not path.exists():
        return None
    from jaxtraffic.paper.plotting import read_learning_curve
    try:
        return read_learning_curve(path)
    except ValueError:
        return None


def _meta(meta: dict[str, Any], eval_config: EvalConfig, grids: dict[str, ControllerGrid], fig7: str,
          init_l2: tuple[float, float]) -> dict[str, Any]:
    """metrics.json's "meta": a copy of the caller's ``meta`` with the grid, plant, scenarios and environment.

    Args:
        grids: the controllers' grids. fig7: the alpha noise reading drawn as figure 7.
        init_l2: the initial condition's L2 deviations (``scenarios.initial_norms``), veh/km and m/s.
    """
    nom = eval_config.nominal()
    meta = dict(meta)
    meta.update({
        "seeds": list(eval_config.seeds),
        "grid": {"n_points": eval_config.n_points, "dx_m": float(nom.dx), "dt_s": eval_config.dt,
                 "horizon_s": eval_config.horizon_s,
                 "n_steps": eval_config.n_steps, "record_every": eval_config.record_every, "scheme": eval_config.scheme,
                 "substeps": eval_config.substeps,
                 "controller_grids": {k: dataclasses.asdict(g) for k, g in grids.items()}},
        "fig7_reading": fig7,
        "nominal": {"alpha": 0.15, "h_bar_s": float(nom.h_bar),
                    "rho_bar_veh_per_km": VEH_PER_KM * float(equilibrium(nom)[0]),
                    "v_bar_m_per_s": float(equilibrium(nom)[1])},
        "initial_L2": {"rho_veh_per_km": init_l2[0], "v_m_per_s": init_l2[1]},
        "scenarios": {s.name: {"plant_delay_s": s.plant_delay, "alpha_noise": s.alpha_noise,
                               "controllers": list(s.controllers), "description": s.description,
                               "noise_hold_s": s.noise_hold_s, "noise_per_node": s.noise_per_node,
                               "noise_model_sees": s.noise_model_sees,
                               "controller_assumed_delay_s": CTRL_DELAY} for s in SCENARIOS},
        "equilibrium_indices": equilibrium_indices(eval_config),
        "robust_grid": {"delays_s": list(eval_config.robust_delays), "alphas": list(eval_config.robust_alphas),
                        "horizon_s": eval_config.robust_horizon_s},
        "jax_version": jax.__version__, "backend": jax.default_backend(), "provenance": provenance(),
    })
    return meta


def _robustness_json(robust: dict[str, dict[str, Any]], eval_config: EvalConfig,
                     table: dict[str, Any] | None = None) -> dict[str, Any]:
    """robustness.json's content: the map's axes, units, each controller's arrays as nested lists and its
    counts by what each controller is told ("table", ``maps.map_table``).

    Args:
        robust: controller -> quantity -> (n_delays, n_alphas) array (``scenarios.run_robustness``).
    """
    return {"delays_s": list(eval_config.robust_delays), "alphas": list(eval_config.robust_alphas),
            "horizon_s": eval_config.robust_horizon_s, "paper_horizon_s": eval_config.horizon_s,
            "late_window_s": LATE_WINDOW_S,
            "units": {"final_rho_L2": "veh/km", "final_v_L2": "m/s", "final_reward": "dimensionless",
                      "diverged": "bool", "final_rho_spatial_std": "veh/km", "diverged_step": "plant steps (-1: never)",
                      "diverged_at_s": "s (null: never)", "final_rho_offset": "veh/km",
                      "late_max_rho_spatial_std": "veh/km (max over the last late_window_s; null: diverged)",
                      "paper_rho_L2": "veh/km", "paper_rho_spatial_std": "veh/km", "paper_diverged": "bool"},
            "note": "arrays indexed [delay][alpha]; controllers told D are told each cell's true plant delay; "
                    "final_*: at horizon_s, paper_*: the same rollout at paper_horizon_s (the paper's column); "
                    "table: counts over the controllable cells (table.rule) and what each controller is told, at "
                    "both horizons and stays_stabilised (late maximum below the threshold, not diverged)",
            "controllers": {c: {k: as_lists(v) for k, v in r.items()} for c, r in robust.items()},
            "table": table or {}}


def _write(out_dir: Path, claims: list, metrics: dict, meta: dict, figures: list, robust: dict, robust_json: dict,
           eval_config: EvalConfig, numerics: dict | None, lc_data: Any, learned_runs: dict | None,
           oracle: dict[str, dict] | None, table: dict[str, Any] | None = None) -> str:
    """robustness.json, metrics.json and claims.json; returns REPORT.md's text."""
    write_json(out_dir / "robustness.json", robust_json)
    write_json(out_dir / "metrics.json", metrics)
    notes = []
    if lc_data is None:
        notes.append("- No learning curve was available, so figure 3a is missing.")
    sections = readings_summary(claims, metrics, eval_config) + numerics_summary(numerics, metrics, eval_config)
    sections += robustness_summary(robust, eval_config, oracle, table) + comparison_section(
        metrics, learned_runs or {}, robust, tuple(eval_config.robust_alphas), tuple(eval_config.robust_delays),
        eval_config.horizon_s, table)
    report = report_text(out_dir, claims, metrics, meta, figures, notes, sections=sections)
    write_json(out_dir / "claims.json", [{**{k: v for k, v in c.items() if k != "checks"},
                                          "checks": [ch.__dict__ for ch in c["checks"]]} for c in claims])
    return report
