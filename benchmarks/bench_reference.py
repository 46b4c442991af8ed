"""Throughput on the paper's grid and on the reference plant, and where the time goes.

Simulated road-seconds per wall second of ``simulate_batch`` (batch ``--batch``, ``--steps`` control steps of
0.1 s, 2 XLA devices by default), for: the bare solver step (``arz_step`` in a scan, no controller, no
metrics), the open loop with the streaming metrics, the pointwise and the filtered three-gain law, backstepping
on its own (paper) grid through the adapter and on the plant's grid itself (its predictor's d linear steps per
control step on the plant's points), and the gradient of a constant-gains objective (forward + backward pass,
checkpointed). Each figure is also given as a fraction of the bare step's throughput on the same plant, measured
in the same run (ratios are what survives this shared machine's noise).

    python benchmarks/bench_reference.py [--batch 512] [--steps 600] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxtraffic as jt
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.model.solver import arz_step
from jaxtraffic.sim.initial import paper_initial_condition


def best_of(fn, repeat: int) -> float:
    jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def bare(plant: jt.TrafficParams, batch: int, steps: int):
    rho0, v0 = paper_initial_condition(plant)
    h = jnp.full_like(rho0, plant.h_bar)

    @jax.jit
    def run(r, v):
        def one(r, v):
            def body(c, _):
                r2, v2, _, _ = arz_step(c[0], c[1], h, plant)
                return (r2, v2), None
            return jax.lax.scan(body, (r, v), None, length=steps)[0]
        return jax.vmap(one)(r, v)

    r = jnp.broadcast_to(rho0, (batch, plant.n_points))
    v = jnp.broadcast_to(v0, (batch, plant.n_points))
    return lambda: run(r, v)


def rollout(plant: jt.TrafficParams, ctrl, batch: int, steps: int):
    params = jt.stack_params(*[plant.replace(delay=float(d)) for d in np.round(np.linspace(0.0, 8.0, batch), 1)])
    return lambda: jt.simulate_batch(params, ctrl, n_steps=steps).metrics["J_TTT"]


def gradient(plant: jt.TrafficParams, batch: int, steps: int):
    params = jt.stack_params(*[plant.replace(delay=4.0)] * batch)

    def objective(g):
        res = jt.simulate_batch(params, adapt(jt.constant_gains(g[0], g[1], g[2], filter_sigma=25.0),
                                              baseline_grid(plant), plant),
                                n_steps=steps, record=jt.Record(every=10), memory=jt.Memory(remat=True))
        return jnp.mean(res.trajectory.reward)

    f = jax.jit(jax.grad(objective))
    g0 = jnp.asarray([-0.2, -0.7, -0.7])
    return lambda: f(g0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    b, n = args.batch, args.steps
    print(f"devices: {jax.devices()}; batch {b}, {n} steps of 0.1 s; road-seconds per wall second (fraction of "
          "the bare step)")
    for name, plant in (("paper grid", jt.TrafficParams()), ("reference plant", jt.TrafficParams.reference())):
        grid = baseline_grid(plant)
        cases = {
            "bare solver step": bare(plant, b, n),
            "open loop (metrics)": rollout(plant, jt.open_loop(), b, n),
            "pointwise gains": rollout(plant, adapt(jt.constant_gains(-0.2, -0.7, -0.7), grid, plant), b, n),
            "filtered gains (25 m)": rollout(plant, adapt(jt.constant_gains(-0.2, -0.7, -0.7, filter_sigma=25.0),
                                                          grid, plant), b, n),
            "backstepping, own grid": rollout(plant, adapt(jt.backstepping(4.0), grid, plant), b, n),
        }
        if plant.n_points != grid.n_points:
            cases["backstepping, plant grid"] = rollout(plant, jt.backstepping(4.0), b, n)
        cases["gradient (fwd+bwd, remat)"] = gradient(plant, b // 8, n)
        base = None
        for case, fn in cases.items():
            envs = b // 8 if case.startswith("gradient") else b
            rate = envs * n * 0.1 / best_of(fn, args.repeat)
            base = rate if base is None else base
            print(f"  {name:15s} | {case:26s} | {rate:10.4g} road-s/s | {rate / base:6.3f} of bare", flush=True)


if __name__ == "__main__":
    main()
