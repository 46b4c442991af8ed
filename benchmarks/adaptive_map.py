"""Adaptive backstepping (control.adaptive) against backstepping on the robustness map (issue 38).

Counts over plant delay x plant alpha (600 s, no noise, the paper's initial condition on the nominal
equilibrium, target and model alpha 0.15): stabilised = not diverged and final spatial std of rho
< 0.5 veh/km; diverged. Rows: backstepping told D; backstepping told D and
the plant's alpha (the information bound; linearised about the plant's own equilibrium at h_bar, and
``_hold``: about the nominal one); adaptive backstepping told D only (the same two linearisations;
``_hold`` is the default); open loop (told nothing, to find the cells
that are inconsistent before any control acts). Every controller acts on the paper's grid (201
points, 0.1 s) through ``control.adapter`` as in ``paper.numerics.deploy``.

    python benchmarks/adaptive_map.py --plant paper                     # the 201-point upwind plant
    python benchmarks/adaptive_map.py --plant reference                 # MUSCL, 801 points, 2 substeps
    python benchmarks/adaptive_map.py --plant refined                   # the reference refined once (1601, 4)
    python benchmarks/adaptive_map.py --plant reference --cells 1       # time one cell per controller
    python benchmarks/adaptive_map.py --trace --plant reference         # the estimate's error over time
    python benchmarks/adaptive_map.py --nominal --plant reference       # rho L2 at 300 s, J_comfort

Writes a JSON summary with ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control import adaptive_backstepping, backstepping, open_loop, tell_delay
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.model.params import equilibrium
from jaxtraffic.paper.scenarios import EvalConfig, run_batch
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import STABLE_STD, VEH_PER_KM, density_std
from jaxtraffic.sim.plant import closed_loop_step, initial_state
from jaxtraffic.sim.units import INDEX_UNITS

DELAYS = tuple(float(d) for d in range(9))  # s
ALPHAS = tuple(float(a) for a in np.round(np.linspace(0.05, 0.6, 6), 6))
STD_TOL = STABLE_STD  # veh/km


def eval_config(plant: str, horizon_s: float = 600.0) -> EvalConfig:
    base = {"reference": EvalConfig.reference(), "refined": EvalConfig.reference(n_points=1601, substeps=4),
            "paper": EvalConfig()}[plant]
    return EvalConfig(**{**base.__dict__, "horizon_s": horizon_s, "robust_delays": DELAYS, "robust_alphas": ALPHAS})


def controllers() -> dict[str, tuple]:
    """name -> (controller, told alpha?)."""
    return {"open_loop": (open_loop(), False), "backstepping": (backstepping(), False),
            "backstepping_alpha": (adaptive_backstepping(adapt=False, hold_target=False), True),
            "adaptive": (adaptive_backstepping(hold_target=False), False),
            "adaptive_hold": (adaptive_backstepping(hold_target=True), False),
            "backstepping_alpha_hold": (adaptive_backstepping(adapt=False, hold_target=True), True)}


def run_map(cfg: EvalConfig, names: list[str], cells: int | None, log=print) -> dict:
    nom = cfg.nominal()
    dd, aa = np.meshgrid(np.asarray(DELAYS), np.asarray(ALPHAS), indexing="ij")
    dd, aa = dd.ravel(), aa.ravel()
    if cells:
        pick = np.array([4 * len(ALPHAS) + 1] if cells == 1 else np.arange(cells))  # (4 s, 0.16) first
        dd, aa = dd[pick], aa[pick]
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(dd, aa, strict=True)]
    out = {"delays": dd.tolist(), "alphas": aa.tolist(), "dt": float(cfg.dt)}
    for name in names:
        ctrl, told_alpha = controllers()[name]
        ctrl = adapt(ctrl, baseline_grid(nom), nom)
        batched = hasattr(ctrl.settings, "delay")
        if batched:
            ctrl = tell_delay(ctrl, jnp.asarray(dd, jnp.float32))
        if told_alpha:
            ctrl = ctrl.replace(settings=ctrl.settings.replace(alpha0=jnp.asarray(aa, jnp.float32)))
        t0 = time.perf_counter()
        res = run_batch(ctrl, envs, [0] * len(envs), cfg, record=False, batch_controller=batched,
                        chunk_size=len(ALPHAS))
        std = VEH_PER_KM * np.std(np.asarray(res.final.rho), axis=-1)
        div = np.asarray(res.metrics["diverged"]).astype(bool)
        entry = {"diverged": div.tolist(), "std": std.tolist(), "final_rho_L2": np.asarray(
            res.metrics["final_rho_L2"]).tolist(), "diverged_step": np.asarray(res.final.diverged_step).tolist()}
        cs = res.controller_state
        if hasattr(cs, "inner") and hasattr(cs.inner, "alpha_hat"):
            entry["alpha_hat"] = np.asarray(cs.inner.alpha_hat).tolist()
        out[name] = entry
        log(f"  {name:<20s} {len(envs):3d} cells x {cfg.n_steps} steps  {time.perf_counter() - t0:7.1f} s")
    return out


def summarise(out: dict, log=print) -> dict:
    """Counts over all cells and over the controllable ones: a cell where the open loop diverges before
    the plant's delay has elapsed (before any controller's input reaches the plant, so every controller
    diverges with it) is inconsistent and excluded; the reason is printed."""
    dd, aa = np.asarray(out["delays"]), np.asarray(out["alphas"])
    excluded = np.zeros(dd.shape, bool)
    if "open_loop" in out:
        ol = out["open_loop"]
        step = np.asarray(ol["diverged_step"])
        dt = out["dt"]
        excluded = np.asarray(ol["diverged"], bool) & (step < np.round(dd / dt))
        for i in np.flatnonzero(np.asarray(ol["diverged"], bool)):
            why = "excluded: before any control acts" if excluded[i] else "kept (control acts before)"
            log(f"  open loop diverges at (D {dd[i]:g} s, alpha {aa[i]:g}) at t = {step[i] * dt:.1f} s: {why}")
    table = {}
    log(f"  {'controller':<20s} {'told':<9s} {'stabilised':>10s} {'diverged':>8s}   (of {int((~excluded).sum())}"
        f" controllable; all {dd.size} cells in brackets)")
    for name, told in (("open_loop", "nothing"), ("backstepping", "D"), ("backstepping_alpha", "D, alpha"),
                       ("adaptive", "D"), ("backstepping_alpha_hold", "D, alpha"), ("adaptive_hold", "D")):
        if name not in out:
            continue
        div = np.asarray(out[name]["diverged"], bool)
        stab = ~div & (np.asarray(out[name]["std"]) < STD_TOL)
        row = {"told": told, "stabilised": int((stab & ~excluded).sum()), "diverged": int((div & ~excluded).sum()),
               "stabilised_all": int(stab.sum()), "diverged_all": int(div.sum())}
        table[name] = row
        log(f"  {name:<20s} {told:<9s} {row['stabilised']:>10d} {row['diverged']:>8d}   "
            f"({row['stabilised_all']}, {row['diverged_all']})")
    for name in ("adaptive", "adaptive_hold"):
        if name not in out or "alpha_hat" not in out[name]:
            continue
        err = np.abs(np.asarray(out[name]["alpha_hat"]) - aa)
        ok = ~excluded & ~np.asarray(out[name]["diverged"], bool)
        worst = np.flatnonzero(ok)[err[ok].argmax()]
        log(f"  {name}: |alpha_hat - alpha| at the end over the controllable non-diverged cells: max "
            f"{err[worst]:.4f} (at D {dd[worst]:g} s, alpha {aa[worst]:g}), median {np.median(err[ok]):.4f}, "
            f"> 0.01 in {int((err[ok] > 0.01).sum())} cells")
    return table


def trace(cfg: EvalConfig, delays, alphas, n_steps: int, every: int, alpha0: float = float("nan"), **estimator):
    """(t, alpha_hat, rho std, diverged) of adaptive backstepping told each plant's delay, on the plants
    (delays[i] s, alphas[i]) from the paper's initial condition, every ``every`` steps; the cells
    run as one vmapped scan. Arrays of shape (cells, n_steps // every)."""
    nom = cfg.nominal()
    estimator = {"hold_target": False, **estimator}
    ctrl = adapt(adaptive_backstepping(alpha0=alpha0, **estimator), baseline_grid(nom), nom)
    rho0, v0 = paper_initial_condition(nom)
    rho_bar, v_bar = equilibrium(nom)

    def run(delay, alpha):
        plant = nom.replace(delay=delay, alpha=alpha)
        c = ctrl.replace(settings=ctrl.settings.replace(delay=delay))
        state = initial_state(plant, rho0, v0)
        cs = c.init(state.observation(plant), nom)

        def step(carry, _):
            state, cs = carry
            state, cs, _, _ = closed_loop_step(state, cs, c, plant, nom, plant.alpha, jax.random.PRNGKey(0),
                                               (rho_bar, v_bar))
            return (state, cs), (cs.inner.alpha_hat, density_std(state.rho), state.diverged)

        def chunk(carry, _):
            carry, rec = jax.lax.scan(step, carry, None, length=every)
            return carry, jax.tree.map(lambda x: x[-1], rec)

        return jax.lax.scan(chunk, (state, cs), None, length=n_steps // every)[1]

    out = jax.jit(jax.vmap(run))(jnp.asarray(delays, jnp.float32), jnp.asarray(alphas, jnp.float32))
    t = (np.arange(n_steps // every) + 1) * every * float(nom.dt)
    return (t, *(np.asarray(x) for x in out))


def print_trace(cfg: EvalConfig, delay: float, alpha: float, alpha0: float, horizon: float, **estimator) -> None:
    n = int(round(horizon / cfg.dt))
    t, a_hat, std, div = trace(cfg, [delay], [alpha], n, 1, alpha0, **estimator)
    a_hat, std, div = a_hat[0], std[0], div[0]
    a0 = 0.15 if np.isnan(alpha0) else alpha0
    print(f"estimate over time: D {delay:g} s, alpha {alpha:g}, estimate starts at {a0:g}")
    for ts in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 30, 60, 100, 150, 200, 250, 300, 400, 500, 600):
        i = int(round(ts / cfg.dt)) - 1
        if i < len(t):
            print(f"  t {t[i]:6.1f} s  alpha_hat {a_hat[i]:.4f}  error {a_hat[i] - alpha:+.4f}  "
                  f"std rho {std[i]:.3f} veh/km  diverged {bool(div[i])}")
    err = np.abs(a_hat - alpha)
    print(f"  max |error| for t >= 1 s: {err[t >= 1].max():.4f}, t >= 10 s: {err[t >= 10].max():.4f}, "
          f"t >= 100 s: {err[t >= 100].max():.4f}")


def print_trace_map(cfg: EvalConfig, horizon: float, alpha0: float, **estimator) -> None:
    """The estimate's error over time across the map (every cell, 1 s samples; the two cells that blow up
    before any control acts left out): the worst cell at each time and the worst after shocks form."""
    dd, aa = (x.ravel() for x in np.meshgrid(np.asarray(DELAYS), np.asarray(ALPHAS), indexing="ij"))
    keep = ~((aa > 0.55) & (dd >= 7))
    dd, aa = dd[keep], aa[keep]
    n = int(round(horizon / cfg.dt))
    t0 = time.perf_counter()
    t, a_hat, std, div = trace(cfg, dd, aa, n, int(round(1.0 / cfg.dt)), alpha0, **estimator)
    err = np.where(div, np.nan, np.abs(a_hat - aa[:, None]))
    err[np.all(np.isnan(err), axis=1)] = -1.0  # a cell diverged from the start: no estimate to judge
    print(f"estimate error across the map ({len(dd)} cells, {time.perf_counter() - t0:.0f} s): worst cell at t")
    for ts in (1, 2, 5, 10, 30, 60, 100, 200, 300, 400, 500, 600):
        i = int(ts) - 1
        if i < len(t):
            j = np.nanargmax(err[:, i])
            print(f"  t {ts:4d} s  max |error| {err[j, i]:.4f} (D {dd[j]:g} s, alpha {aa[j]:g})  "
                  f"median {np.nanmedian(err[:, i]):.5f}  std rho > 5 veh/km in {int((std[:, i] > 5.0).sum())} cells")
    for since in (10, 60, 300):
        e = np.nanmax(err[:, t >= since], axis=1)
        j = np.nanargmax(e)
        print(f"  worst |error| over t >= {since} s: {e[j]:.4f} (D {dd[j]:g} s, alpha {aa[j]:g})")


def nominal_point(cfg: EvalConfig) -> None:
    """Density L2 at 300 s and J_comfort of backstepping and adaptive backstepping at D = 4 s, alpha = 0.15."""
    cfg300 = EvalConfig(**{**cfg.__dict__, "horizon_s": 300.0})
    nom = cfg300.nominal()
    env = [nom.replace(delay=4.0)]
    for name, c in (("backstepping", backstepping(4.0)),
                    ("adaptive", adaptive_backstepping(4.0, hold_target=False)),
                    ("adaptive_hold", adaptive_backstepping(4.0, hold_target=True))):
        res = run_batch(adapt(c, baseline_grid(nom), nom), env, [0], cfg300, record=False)
        m = res.metrics
        print(f"  nominal point (D 4 s, alpha 0.15), {name:<13s} rho L2 300 s {float(m['final_rho_L2'][0]):.4f}"
              f" veh/km  J_comfort {float(m['J_comfort'][0]):.5g} {INDEX_UNITS['J_comfort']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", choices=("paper", "reference", "refined"), default="paper")
    ap.add_argument("--controllers", default="open_loop,backstepping,backstepping_alpha,adaptive,"
                    "backstepping_alpha_hold,adaptive_hold")
    ap.add_argument("--cells", type=int, default=0, help="run only the first N cells (1: the cell (4 s, 0.16))")
    ap.add_argument("--horizon", type=float, default=600.0)
    ap.add_argument("--trace", action="store_true", help="the estimate over time at (--delay, --alpha) and the map")
    ap.add_argument("--nominal", action="store_true", help="rho L2 at 300 s and J_comfort at D 4 s, alpha 0.15")
    ap.add_argument("--delay", type=float, default=4.0)
    ap.add_argument("--alpha", type=float, default=0.15)
    ap.add_argument("--alpha0", type=float, default=float("nan"), help="initial estimate (default: nominal 0.15)")
    ap.add_argument("--forgetting", type=float, default=0.99, help="trace: the estimator's forgetting factor")
    ap.add_argument("--shock-scale", type=float, default=2e-3, help="trace: its shock weight scale, veh/m (inf: none)")
    ap.add_argument("--resid-scale", type=float, default=0.0, help="trace: its residual weight scale, m/s (0: off)")
    ap.add_argument("--no-map", action="store_true", help="trace: the single cell only")
    ap.add_argument("--hold", action="store_true", help="trace: the default law (hold_target) instead of the plain one")
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    cfg = eval_config(args.plant, args.horizon)
    if args.trace:
        est = {"forgetting": args.forgetting, "shock_scale": args.shock_scale, "hold_target": args.hold,
               "resid_scale": args.resid_scale}
        print(f"estimator: {est}")
        print_trace(cfg, args.delay, args.alpha, args.alpha0, args.horizon, **est)
        if not args.no_map:
            print_trace_map(cfg, args.horizon, args.alpha0, **est)
        return
    if args.nominal:
        nominal_point(cfg)
        return
    t0 = time.perf_counter()
    out = run_map(cfg, args.controllers.split(","), args.cells or None)
    print(f"plant {args.plant}: {time.perf_counter() - t0:.1f} s")
    out["table"] = summarise(out) if not args.cells else {}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f)


if __name__ == "__main__":
    main()
