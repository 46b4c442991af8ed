"""Throughput on whatever backend JAX finds (issue 48.4): cell updates per second of ``simulate_batch`` with every
metric (the default call) and with none (``metrics=()``) at batch 1 024 to 65 536, and the PPO environment's steps
per second (``learn.env.step_env`` under ``vmap`` in a ``scan``, random actions).

Nothing here forces a platform: on a GPU it runs there (``Memory``'s "auto" chunking: one vmap over the batch; the
predictor and the environment's reset in their accelerator forms), on a CPU on the CPU. The batch is capped by
``--max-batch`` (default 65 536 on an accelerator, 4 096 on a CPU). Lyapunov at D = 4 s on the paper grid (201 points,
upwind), no trajectory; each figure is the best of ``--repeats`` calls after one compiling call (wall time, the
device synchronised). The goal on one H100 (issue 48): at least 1e10 cell updates/s at batch 65 536 without metrics.

    python benchmarks/bench_accelerator.py                         # everything the backend allows
    python benchmarks/bench_accelerator.py --max-batch 1024 --steps 100 --env-batches 256 --json
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
from machine import cpu_model

from jaxtraffic import TrafficParams, lyapunov, paper_initial_condition, simulate_batch
from jaxtraffic.learn import env as learn_env

D = 4.0  # s, the plant's delay
BATCHES = (1024, 4096, 16384, 65536)


def _args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch-sizes", default=",".join(map(str, BATCHES)))
    ap.add_argument("--max-batch", type=int, default=None,
                    help="largest batch run (default 65536 on an accelerator, 4096 on a CPU)")
    ap.add_argument("--steps", type=int, default=300, help="steps per rollout")
    ap.add_argument("--env-batches", default="1024,16384", help="PPO environment batch sizes ('' to skip)")
    ap.add_argument("--env-steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    return ap.parse_args(argv)


def best_wall(fn, *args, repeats: int) -> float:
    """Best wall time (s) of ``repeats`` calls after one compiling call."""
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def rollout_rates(batch: int, steps: int, repeats: int) -> dict[str, float]:
    """Cell updates/s of the default call and of the metric-free one at ``batch``."""
    p = TrafficParams(delay=D)
    rho0, v0 = jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(jnp.linspace(0.005, 0.015, batch))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    ctrl, cells = lyapunov(), batch * steps * p.n_points
    out = {}
    for name, names in (("default", None), ("no_metrics", ())):
        fn = jax.jit(lambda r, v, k, names=names: simulate_batch(p, ctrl, n_steps=steps, rho0=r, v0=v, keys=k,
                                                                 metrics=names))
        out[name] = cells / best_wall(fn, rho0, v0, keys, repeats=repeats)
    return out


def env_rate(batch: int, steps: int, repeats: int) -> float:
    """PPO environment steps/s at ``batch`` environments (the default environment, random actions)."""
    ep = learn_env.make_env_params()
    _, state = jax.vmap(learn_env.reset_env, (0, None))(jax.random.split(jax.random.PRNGKey(1), batch), ep)
    actions = jax.random.normal(jax.random.PRNGKey(2), (steps, batch, 3))

    @jax.jit
    def run(state, actions):
        def body(c, a):
            st, k = c
            k, sub = jax.random.split(k)
            obs, st, r, _, _ = jax.vmap(learn_env.step_env, (0, 0, 0, None))(jax.random.split(sub, batch), st, a, ep)
            return (st, k), r.sum() + obs.sum()  # (the observation is used, as in training)
        return jax.lax.scan(body, (state, jax.random.PRNGKey(3)), actions)

    return batch * steps / best_wall(run, state, actions, repeats=repeats)


def main(argv: list[str] | None = None) -> dict:
    args = _args(argv)
    backend = jax.default_backend()
    cap = args.max_batch or (4096 if backend == "cpu" else max(BATCHES))
    batches = [b for b in (int(x) for x in args.batch_sizes.split(",") if x) if b <= cap]
    env_batches = [b for b in (int(x) for x in args.env_batches.split(",") if x) if b <= cap]
    out = {"backend": backend, "devices": [str(d) for d in jax.devices()], "host_cpu": cpu_model(),
           "steps": args.steps, "controller": f"lyapunov, D = {D:g} s, paper grid (201 points)",
           "rollout_cell_updates_per_s": {b: rollout_rates(b, args.steps, args.repeats) for b in batches},
           "env_steps_per_s": {b: env_rate(b, args.env_steps, args.repeats) for b in env_batches}}
    if args.json:
        print(json.dumps(out, indent=1))
        return out
    print(f"backend {backend}: {out['devices'][0]} x{len(out['devices'])} (host {out['host_cpu']}); "
          f"{args.steps} steps, {out['controller']}")
    for b, r in out["rollout_cell_updates_per_s"].items():
        print(f"  batch {b:6d}: default {r['default']:9.3g} cell updates/s, no metrics {r['no_metrics']:9.3g}"
              f" cell updates/s (x{r['no_metrics'] / r['default']:.2f})")
    for b, r in out["env_steps_per_s"].items():
        print(f"  PPO environment, {b:6d} envs: {r:9.3g} env steps/s")
    return out


if __name__ == "__main__":
    main()
