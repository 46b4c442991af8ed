"""Adaptive backstepping (control.adaptive) against backstepping on the robustness map (issue 38).

Counts over plant delay x plant alpha (600 s, no noise, the paper's initial condition on the nominal
equilibrium, target and model alpha 0.15): stabilised = not diverged and final spatial std of rho
< 0.5 veh/km; diverged. Rows: backstepping told D; backstepping told D and the plant's alpha (the
information bound); adaptive backstepping told D only; open loop (told nothing, to find the cells
that are inconsistent before any control acts). Every controller acts on the paper's grid (201
points, 0.1 s) through ``control.adapter`` as in ``paper.numerics.deploy``.

    python benchmarks/adaptive_map.py --plant paper                     # the 201-point upwind plant
    python benchmarks/adaptive_map.py --plant reference                 # MUSCL, 801 points, 2 substeps
    python benchmarks/adaptive_map.py --plant reference --cells 1       # time one cell per controller
    python benchmarks/adaptive_map.py --trace --plant paper             # the estimate's error over time

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
from jaxtraffic.sim.plant import closed_loop_step, initial_state

DELAYS = tuple(float(d) for d in range(9))  # s
ALPHAS = tuple(float(a) for a in np.round(np.linspace(0.05, 0.6, 6), 6))
STD_TOL = 0.5e-3  # veh/m: 0.5 veh/km


def eval_config(plant: str, horizon_s: float = 600.0) -> EvalConfig:
    base = EvalConfig.reference() if plant == "reference" else EvalConfig()
    return EvalConfig(**{**base.__dict__, "horizon_s": horizon_s, "robust_delays": DELAYS, "robust_alphas": ALPHAS})


def controllers() -> dict[str, tuple]:
    """name -> (controller, told alpha?)."""
    return {"open_loop": (open_loop(), False), "backstepping": (backstepping(), False),
            "backstepping_alpha": (adaptive_backstepping(adapt=False), True),
            "adaptive": (adaptive_backstepping(), False)}


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
        std = np.std(np.asarray(res.final.rho), axis=-1)
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
                       ("adaptive", "D")):
        if name not in out:
            continue
        div = np.asarray(out[name]["diverged"], bool)
        stab = ~div & (np.asarray(out[name]["std"]) < STD_TOL)
        row = {"told": told, "stabilised": int((stab & ~excluded).sum()), "diverged": int((div & ~excluded).sum()),
               "stabilised_all": int(stab.sum()), "diverged_all": int(div.sum())}
        table[name] = row
        log(f"  {name:<20s} {told:<9s} {row['stabilised']:>10d} {row['diverged']:>8d}   "
            f"({row['stabilised_all']}, {row['diverged_all']})")
    if "adaptive" in out and "alpha_hat" in out["adaptive"]:
        err = np.abs(np.asarray(out["adaptive"]["alpha_hat"]) - aa)
        ok = ~excluded & ~np.asarray(out["adaptive"]["diverged"], bool)
        worst = np.flatnonzero(ok)[err[ok].argmax()]
        log(f"  adaptive: |alpha_hat - alpha| at the end over the controllable non-diverged cells: max "
            f"{err[worst]:.4f} (at D {dd[worst]:g} s, alpha {aa[worst]:g}), median {np.median(err[ok]):.4f}")
    return table


def trace(cfg: EvalConfig, delay: float, alpha: float, n_steps: int, every: int, alpha0: float = float("nan")):
    """(t, alpha_hat, rho L2) of adaptive backstepping told ``delay`` on the plant (``delay``, ``alpha``)
    from the paper's initial condition, every ``every`` steps."""
    nom = cfg.nominal()
    plant = nom.replace(delay=delay, alpha=alpha)
    ctrl = adapt(adaptive_backstepping(delay=delay, alpha0=alpha0), baseline_grid(nom), nom)
    rho0, v0 = paper_initial_condition(nom)
    rho_bar, v_bar = equilibrium(nom)

    @jax.jit
    def run(plant):
        state = initial_state(plant, rho0, v0)
        cs = ctrl.init(state.observation(plant), nom)

        def step(carry, n):
            state, cs = carry
            state, cs, _, _ = closed_loop_step(state, cs, ctrl, plant, nom, plant.alpha, jax.random.PRNGKey(0),
                                               (rho_bar, v_bar))
            return (state, cs), (cs.inner.alpha_hat, jnp.sqrt(jnp.mean((state.rho - rho_bar) ** 2)),
                                 jnp.std(state.rho), state.diverged)

        _, rec = jax.lax.scan(step, (state, cs), jnp.arange(n_steps))
        return rec

    a_hat, l2, std, div = (np.asarray(x) for x in run(plant))
    t = (np.arange(n_steps) + 1) * float(nom.dt)
    sel = slice(every - 1, None, every)
    return t[sel], a_hat[sel], l2[sel], std[sel], div[sel]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plant", choices=("paper", "reference"), default="paper")
    ap.add_argument("--controllers", default="open_loop,backstepping,backstepping_alpha,adaptive")
    ap.add_argument("--cells", type=int, default=0, help="run only the first N cells (1: the cell (4 s, 0.16))")
    ap.add_argument("--horizon", type=float, default=600.0)
    ap.add_argument("--trace", action="store_true", help="the estimate over time at (--delay, --alpha)")
    ap.add_argument("--delay", type=float, default=4.0)
    ap.add_argument("--alpha", type=float, default=0.15)
    ap.add_argument("--alpha0", type=float, default=float("nan"), help="initial estimate (default: nominal 0.15)")
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    cfg = eval_config(args.plant, args.horizon)
    if args.trace:
        n = int(round(args.horizon / cfg.dt))
        t, a_hat, l2, std, div = trace(cfg, args.delay, args.alpha, n, int(round(1.0 / cfg.dt)),
                                       args.alpha0)
        a0 = 0.15 if np.isnan(args.alpha0) else args.alpha0
        print(f"plant {args.plant}, D {args.delay:g} s, alpha {args.alpha:g} (estimate starts at {a0:g})")
        for ts in (1, 2, 5, 10, 20, 30, 60, 100, 150, 200, 250, 300, 400, 500, 600):
            i = int(round(ts)) - 1
            if i < len(t):
                print(f"  t {t[i]:6.0f} s  alpha_hat {a_hat[i]:.4f}  error {a_hat[i] - args.alpha:+.4f}  "
                      f"rho L2 {1e3 * l2[i]:.3f} veh/km  std {1e3 * std[i]:.3f} veh/km  diverged {bool(div[i])}")
        err = np.abs(a_hat - args.alpha)
        print(f"  max |error| over t >= 10 s: {err[t >= 10].max():.4f}; over t >= 100 s: {err[t >= 100].max():.4f}")
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
