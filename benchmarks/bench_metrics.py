"""What the metrics cost: CPU time per cell update of ``simulate_batch`` with every metric (the default call),
with the selections the library's callers make (``metrics=``, issue 48.1) and with none (``metrics=()``, the
bare closed loop: plant, controller, delay line, divergence checks), as ratios measured in one process.

Lyapunov at D = 4 s on the paper grid (201 points, upwind), no trajectory, one XLA device. The variants are
timed interleaved, each figure the best of ``--repeats`` calls after one compiling call; CPU time is the
process's (``time.process_time``: the machine is shared, wall time is noisier), wall time is reported beside it.

    python benchmarks/bench_metrics.py                   # batch 64 and 1024, 300 steps
    python benchmarks/bench_metrics.py --batch-sizes 64 --steps 100 --repeats 2 --json
    python benchmarks/bench_metrics.py --singles         # also each running sum alone: its marginal cost

``--singles`` adds one variant per running sum (a metric that reads only it: J_TTT, J_fuel, max_cfl,
control_effort, J_comfort_a2, J_comfort, J_comfort_at2, J_comfort_switch_on, J_fuel_kmh), so that the
cost of each pass over the batch that the default call makes for its sums can be read off.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
from machine import cpu_model, load

from jaxtraffic import TrafficParams, lyapunov, paper_initial_condition, simulate_batch
from jaxtraffic.paper.scenarios import ROBUST_METRICS
from jaxtraffic.runs.ppo.selection import SUITE_METRICS

VARIANTS = {"default (all metrics)": None, "PPO suite's selection": SUITE_METRICS,
            "robustness map's selection": ROBUST_METRICS, "no metrics": ()}
SINGLES = ("J_TTT", "J_fuel", "max_cfl", "control_effort", "J_comfort_a2", "J_comfort", "J_comfort_at2",
           "J_comfort_switch_on", "J_fuel_kmh")  # each reads one running sum (and a_prev for the comfort ones)
D = 4.0  # s, the plant's delay (the delay line is part of the closed loop)


def _args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch-sizes", default="64,1024")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--singles", action="store_true", help="also each running sum alone (SINGLES)")
    ap.add_argument("--json", action="store_true")
    return ap.parse_args(argv)


def _call(p: TrafficParams, steps: int, names):
    ctrl = lyapunov()
    # the whole result: a jitted caller that dropped the metrics would let JAX remove their sums anyway
    return jax.jit(lambda r, v, k: simulate_batch(p, ctrl, n_steps=steps, rho0=r, v0=v, keys=k, metrics=names))


def measure(batch: int, steps: int, repeats: int, singles: bool = False) -> dict[str, dict[str, float]]:
    """name -> {cpu_ns, wall_ns} per cell update (best of ``repeats``), the variants interleaved."""
    p = TrafficParams(delay=D)
    rho0, v0 = jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(jnp.linspace(0.005, 0.015, batch))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    variants = {**VARIANTS, **({f"{k} alone": (k,) for k in SINGLES} if singles else {})}
    fns = {name: _call(p, steps, names) for name, names in variants.items()}
    for fn in fns.values():
        jax.block_until_ready(fn(rho0, v0, keys))  # compile
    best = {name: [float("inf"), float("inf")] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            c0, w0 = time.process_time(), time.perf_counter()
            jax.block_until_ready(fn(rho0, v0, keys))
            c, w = time.process_time() - c0, time.perf_counter() - w0
            best[name] = [min(best[name][0], c), min(best[name][1], w)]
    cells = batch * steps * p.n_points
    return {name: {"cpu_ns": 1e9 * c / cells, "wall_ns": 1e9 * w / cells} for name, (c, w) in best.items()}


def main(argv: list[str] | None = None) -> dict:
    args = _args(argv)
    out = {"machine": cpu_model(), "load_before": load(), "devices": [str(d) for d in jax.devices()],
           "steps": args.steps, "controller": f"lyapunov, D = {D:g} s, paper grid", "batches": {}}
    for b in (int(x) for x in args.batch_sizes.split(",")):
        out["batches"][b] = measure(b, args.steps, args.repeats, args.singles)
    out["load_after"] = load()
    if args.json:
        print(json.dumps(out, indent=1))
        return out
    print(f"{out['machine']}, {out['devices'][0]} x{len(out['devices'])}, {args.steps} steps, {out['controller']}; "
          f"load {out['load_before']} -> {out['load_after']}")
    for b, rows in out["batches"].items():
        free = rows["no metrics"]["cpu_ns"]
        print(f"batch {b}:")
        for name, r in rows.items():
            print(f"  {name:<28s} {r['cpu_ns']:6.2f} ns CPU ({r['wall_ns']:6.2f} ns wall) per cell update"
                  f"   x{r['cpu_ns'] / free:4.2f} the metric-free loop")
    return out


if __name__ == "__main__":
    main()
