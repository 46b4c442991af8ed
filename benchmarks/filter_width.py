"""The learned gain law's spatial filter: which width, measured (BENCHMARKS.md "The learned law's spatial filter").

For each filter width sigma (m), trains the three constant gains by gradient on the reference plant
(``train.py gradient --policy gains`` with the reference discretisation and the controller on the
paper's grid), then reports: the certificate of the trained gains (max growth rate over wavenumbers, 1/s),
the closed loop at D = 4 s on the reference plant and on the plant refined twice (density L2 at 300 s in
veh/km, J_comfort) next to backstepping, and the training time. ``--sigmas 0`` is the paper's pointwise law.

    python benchmarks/filter_width.py --sigmas 0,10,15,20,25,30 --root /tmp/fw [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jaxtraffic as jt
from jaxtraffic.cli import train as train_cli
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.runs.policy import load_policy, policy_certificate, policy_grid


def judge(ctrl, grid, plant: jt.TrafficParams) -> dict[str, float]:
    res = jt.simulate(plant, adapt(ctrl, grid, plant), n_steps=3000)
    return {"rho_L2_300_veh_km": float(res.metrics["final_rho_L2"]), "J_comfort": float(res.metrics["J_comfort"]),
            "diverged": bool(res.metrics["diverged"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sigmas", default="0,10,15,20,25,30")
    ap.add_argument("--root", type=Path, default=Path("runs/filter-width"))
    ap.add_argument("--extra", default="", help="more train.py flags, comma separated")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    ref = jt.TrafficParams.reference(delay=4.0)
    fine = ref.replace(n_points=2 * ref.n_points - 1, substeps=2 * ref.substeps)
    plant_flags = ["--n-points", str(ref.n_points), "--scheme", "muscl", "--substeps", str(ref.substeps),
                   "--controller-points", "201"]
    bs = {name: judge(jt.backstepping(4.0), baseline_grid(p), p) for name, p in (("reference", ref), ("refined", fine))}
    print(f"backstepping: reference {bs['reference']}, refined {bs['refined']}")
    rows = []
    for sigma in (float(x) for x in args.sigmas.split(",")):
        run = args.root / f"sigma-{sigma:g}"
        t0 = time.perf_counter()
        if not (run / "summary.json").exists():
            train_cli.main(["gradient", "--policy", "gains", "--filter-sigma", str(sigma), *plant_flags,
                            "--out-dir", str(run), "--quiet", *[f for f in args.extra.split(",") if f]])
        wall = time.perf_counter() - t0
        ctrl, config = load_policy(run)
        cert = policy_certificate(ctrl, config)
        row = {"sigma_m": sigma, "train_s": round(wall, 1), "gains": cert["gains"], "max_growth": cert["max_growth"],
               "worst_wavelength_m": cert["worst_wavelength"], "certified": cert["stable"],
               "reference": judge(ctrl, policy_grid(config), ref), "refined": judge(ctrl, policy_grid(config), fine)}
        r, f = row["reference"], row["refined"]
        row["refined_change_L2"] = f["rho_L2_300_veh_km"] / r["rho_L2_300_veh_km"] - 1.0
        row["refined_change_J_comfort"] = f["J_comfort"] / r["J_comfort"] - 1.0
        rows.append(row)
        verdict = "certified" if cert["stable"] else "not certified"
        print(f"sigma {sigma:5g} m | gains ({', '.join(f'{g:+.2f}' for g in cert['gains'])}) | growth "
              f"{cert['max_growth']:+.4f}/s at {cert['worst_wavelength']:.0f} m ({verdict}) | "
              f"reference L2 {r['rho_L2_300_veh_km']:.3f} J_c {r['J_comfort']:.4g} | "
              f"refined {row['refined_change_L2']:+.1%} "
              f"/ {row['refined_change_J_comfort']:+.1%} | {wall:.0f} s", flush=True)
    if args.json:
        print(json.dumps({"backstepping": bs, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
