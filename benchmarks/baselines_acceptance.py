"""Acceptance figures of the model-based baselines (Lyapunov, backstepping) on the paper's grid.

Paper grid (201 points, dx = 5 m, dt = 0.1 s), paper initial condition, 300 s, nonlinear ARZ
plant (first-order upwind). For each case: the L2 norms of the density and speed deviations at
t = 0 and t = 300 s, the times at which they first fall below half / a tenth of their initial
value (to show which converges first), the paper's indices J_TTT, J_fuel, J_comfort (rho in
veh/km), the final reward, the time after which the reward stays >= -0.1, and the wall time of
one (already compiled) rollout.

Usage (from the repository root):
    python benchmarks/baselines_acceptance.py            # table
    python benchmarks/baselines_acceptance.py --json     # JSON list of rows (null: never)
Options: --seconds T (default 300), --noise-seeds S (alpha-noise case: report seed 0 and the
spread over S seeds, default 8).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxtraffic import (  # noqa: E402
    TrafficParams,
    backstepping,
    lyapunov,
    open_loop,
    paper_initial_condition,
    simulate,
    simulate_batch,
    steps_for,
)
from jaxtraffic.sim import Record  # noqa: E402

RECORD_EVERY = 10  # 1 s


# Mean of the plant's noisy alpha, E[clip(0.15 + 0.15 Z, 0, 1)] = 0.15 + 0.15 (phi(1) - Phi(-1)):
# a noise-free plant with this alpha separates the offset of section 12 from the noise itself.
ALPHA_MEAN_NOISY = 0.15 + 0.15 * (math.exp(-0.5) / math.sqrt(2 * math.pi) - 0.5 * math.erfc(1 / math.sqrt(2)))


def cases():
    """(name, plant, controller, nominal[, seconds]) for every acceptance case; nominal None =
    plant; seconds None = the common horizon."""
    nom4 = TrafficParams(delay=4.0)
    return [
        ("open loop, D=0", TrafficParams(), open_loop(), None),
        ("Lyapunov k=1, D=0", TrafficParams(), lyapunov(1.0), None),
        ("Lyapunov nonlinear k=1, D=0", TrafficParams(), lyapunov(1.0, nonlinear=True), None),
        ("Lyapunov k=1, D=4", TrafficParams(delay=4.0), lyapunov(1.0), None),
        ("backstepping Dc=4, D=4", TrafficParams(delay=4.0), backstepping(4.0), None),
        ("backstepping Dc=4, D=3", TrafficParams(delay=3.0), backstepping(4.0), None),
        ("backstepping Dc=4, D=5", TrafficParams(delay=5.0), backstepping(4.0), None),
        ("backstepping Dc=4, D=4, alpha noise 0.15", TrafficParams(delay=4.0, alpha_noise=0.15),
         backstepping(4.0), nom4),
        (f"backstepping Dc=4, D=4, alpha={ALPHA_MEAN_NOISY:.4f}",
         TrafficParams(delay=4.0, alpha=ALPHA_MEAN_NOISY), backstepping(4.0), nom4),
        ("Lyapunov k=1, D=4, alpha noise 0.15", TrafficParams(delay=4.0, alpha_noise=0.15),
         lyapunov(1.0), nom4),
        ("Lyapunov k=1, D=4, 900 s", TrafficParams(delay=4.0), lyapunov(1.0), None, 900.0),
    ]


def _first_below(t: np.ndarray, x: np.ndarray, level: float) -> float:
    idx = np.flatnonzero(x < level)
    return float(t[idx[0]]) if idx.size else math.inf


def run_case(name, plant, controller, nominal, seconds=None, *, n_steps, noise_seeds):
    if seconds is not None:
        n_steps = steps_for(plant, seconds)
        n_steps -= n_steps % RECORD_EVERY
    rho0, v0 = paper_initial_condition(plant if nominal is None else nominal)  # nominal IC (section 12)
    kw = dict(n_steps=n_steps, rho0=rho0, v0=v0, nominal=nominal, record=Record(every=RECORD_EVERY))
    res = simulate(plant, controller, key=jax.random.PRNGKey(0), **kw)
    jax.block_until_ready(res)
    t0 = time.perf_counter()
    jax.block_until_ready(simulate(plant, controller, key=jax.random.PRNGKey(0), **kw))
    wall = time.perf_counter() - t0
    tr, m = res.trajectory, {k: float(v) for k, v in res.metrics.items()}
    t = np.asarray(tr.t)
    r_l2, v_l2 = np.asarray(tr.rho_L2), np.asarray(tr.v_L2)
    row = {
        "case": name,
        "seconds": n_steps * float(plant.dt),
        "rho_L2_0_vehkm": float(r_l2[0]),
        "rho_L2_T_vehkm": m["final_rho_L2"],
        "rho_ratio": m["final_rho_L2"] / float(r_l2[0]),
        "v_L2_0": float(v_l2[0]),
        "v_L2_T": m["final_v_L2"],
        "t_rho_half": _first_below(t, r_l2, 0.5 * r_l2[0]),
        "t_v_half": _first_below(t, v_l2, 0.5 * v_l2[0]),
        "t_rho_tenth": _first_below(t, r_l2, 0.1 * r_l2[0]),
        "t_v_tenth": _first_below(t, v_l2, 0.1 * v_l2[0]),
        "J_TTT": m["J_TTT"],
        "J_fuel": m["J_fuel"],
        "J_comfort": m["J_comfort"],
        "final_reward": m["final_reward"],
        "t_reward_0.1": m["time_to_reward_target_s"],
        "diverged_at_s": m["diverged_at_s"],
        "control_effort_s": m["control_effort"],
        "rollout_wall_s": wall,
    }
    if plant.alpha_noise and noise_seeds > 1:
        keys = jax.random.split(jax.random.PRNGKey(1), noise_seeds)
        b = simulate_batch(plant, controller, keys=keys, n_steps=n_steps, rho0=rho0, v0=v0, nominal=nominal)
        fr = np.asarray(b.metrics["final_reward"])
        frl = np.asarray(b.metrics["final_rho_L2"])
        row["seeds"] = noise_seeds
        row["final_reward_seeds_min_median_max"] = [float(fr.min()), float(np.median(fr)), float(fr.max())]
        row["rho_L2_T_vehkm_seeds_min_median_max"] = [float(frl.min()), float(np.median(frl)),
                                                       float(frl.max())]
    return row


def _fmt(x, spec):
    return "inf" if isinstance(x, float) and math.isinf(x) else format(x, spec)


def print_table(rows, seconds):
    print(f"Paper grid (201 pts, dt 0.1 s), paper IC, {seconds:g} s, nonlinear upwind plant, "
          f"jax {jax.__version__} on {jax.default_backend()}")
    hdr = (f"{'case':42s} {'rhoL2 0->T veh/km':>18s} {'ratio':>6s} {'vL2 0->T m/s':>16s} "
           f"{'t1/2 rho,v s':>13s} {'t1/10 rho,v s':>14s} {'J_TTT':>9s} {'J_fuel':>9s} {'J_comf':>8s} "
           f"{'r(T)':>9s} {'t(r>-.1)':>8s} {'wall s':>6s}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        if r["seconds"] != seconds:
            print(f"  (next row: horizon {r['seconds']:g} s, t1/2, t1/10 and J's over it)")
        print(f"{r['case']:42s} {r['rho_L2_0_vehkm']:7.3f} -> {r['rho_L2_T_vehkm']:7.4f} "
              f"{r['rho_ratio']:6.3f} {r['v_L2_0']:6.3f} -> {r['v_L2_T']:6.4f} "
              f"{_fmt(r['t_rho_half'], '5.0f'):>6s},{_fmt(r['t_v_half'], '5.0f'):>6s} "
              f"{_fmt(r['t_rho_tenth'], '5.0f'):>6s},{_fmt(r['t_v_tenth'], '5.0f'):>7s} "
              f"{r['J_TTT']:9.4g} {r['J_fuel']:9.4g} {r['J_comfort']:8.3g} {r['final_reward']:9.3g} "
              f"{_fmt(r['t_reward_0.1'], '8.1f'):>8s} {r['rollout_wall_s']:6.2f}")
        if not math.isinf(r["diverged_at_s"]):
            print(f"{'':42s} diverged (left the physical region) at {r['diverged_at_s']:.1f} s")
        if "seeds" in r:
            lo, med, hi = r["final_reward_seeds_min_median_max"]
            rlo, rmed, rhi = r["rho_L2_T_vehkm_seeds_min_median_max"]
            print(f"{'':42s} over {r['seeds']} noise seeds: r(T) min/median/max {lo:.3g}/{med:.3g}/{hi:.3g}, "
                  f"rhoL2(T) {rlo:.3f}/{rmed:.3f}/{rhi:.3f} veh/km")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print a JSON list instead of the table")
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--noise-seeds", type=int, default=8)
    args = ap.parse_args(argv)
    n_steps = steps_for(TrafficParams(), args.seconds)
    n_steps -= n_steps % RECORD_EVERY
    rows = [run_case(*c, n_steps=n_steps, noise_seeds=args.noise_seeds) for c in cases()]
    if args.json:  # inf (never reached / never diverged) becomes null
        clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
                 for r in rows]
        print(json.dumps(clean, indent=1))
    else:
        print_table(rows, n_steps * 0.1)


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing anything
    main()
