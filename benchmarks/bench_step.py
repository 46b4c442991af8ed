"""Cost of one simulator step, as ratios measured in one process (issue 39).

Two tables:

1. **x numpy**: ``simulate_batch`` (the default public call: streaming metrics, divergence checks,
   no trajectory) against the same closed loop written as batched numpy (``numpy_ref``: upwind ARZ step,
   the controller, the delay line when D > 0; no metrics, no checks), for open loop, Lyapunov, constant
   gains (pointwise) and backstepping (D = D_ctrl = 4 s, its predictor's 40 linear steps), at each batch
   size, interleaved in the same process. Paper grid (201 points, upwind) only: numpy has no MUSCL.
2. **breakdown of a step** (Lyapunov at D = 4 s on the paper grid; ``--reference`` adds the
   reference plant, 801 points MUSCL, 2 solver steps): the bare ARZ step (a scan of ``arz_step``
   under ``vmap``) = 1; + the controller (law and saturation); + the delay line (push and read);
   + the checks (``sim.plant.closed_loop_step``: physicality, reward, CFL, freeze); the full public call.

And the PPO environment's steps per second (``learn.env.step_env`` under ``vmap`` in a ``scan``,
random actions) at ``--env-batches``: with the reset only where an episode ended and with main's select of a
fresh episode everywhere (``learn.env.RESET_ONLY_WHERE_DONE``), interleaved in the same process.

Each figure is the best of ``--repeats`` timed calls after one compiling call. One XLA device (the
ratios compare like with like: numpy is single-threaded); ``--devices N`` splits the host.

    python benchmarks/bench_step.py                       # both tables and the environment
    python benchmarks/bench_step.py --batch-sizes 1,64 --steps 200 --repeats 2 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
ap.add_argument("--batch-sizes", default="1,64,1024")
ap.add_argument("--steps", type=int, default=300, help="steps per timed JAX rollout")
ap.add_argument("--numpy-steps", type=int, default=60, help="steps per timed numpy rollout (scaled)")
ap.add_argument("--repeats", type=int, default=3)
ap.add_argument("--controllers", default="open_loop,lyapunov,constant_gains,backstepping")
ap.add_argument("--reference", action="store_true", help="also the breakdown on the reference plant")
ap.add_argument("--env-batches", default="64,1024", help="PPO environment batch sizes ('' to skip)")
ap.add_argument("--env-steps", type=int, default=200)
ap.add_argument("--skip", default="", help="comma-separated parts to skip: numpy, breakdown")
ap.add_argument("--devices", type=int, default=1)
ap.add_argument("--json", action="store_true")
ARGS = ap.parse_args()
os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={ARGS.devices}"

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import numpy_ref  # noqa: E402  (benchmarks/numpy_ref.py)
from machine import cpu_model  # noqa: E402

import jaxtraffic  # noqa: E402
from jaxtraffic import Memory, TrafficParams, paper_initial_condition, simulate_batch  # noqa: E402
from jaxtraffic.control.base import saturate  # noqa: E402
from jaxtraffic.model import delay as delay_buffer  # noqa: E402
from jaxtraffic.model.params import equilibrium  # noqa: E402
from jaxtraffic.model.solver import arz_step  # noqa: E402
from jaxtraffic.sim.plant import closed_loop_step, initial_state  # noqa: E402

GAINS = (0.2, -0.5, 0.5)  # constant gains (pointwise law), dimensionless
D = 4.0  # s, the delay of the backstepping row and of the breakdown


def controller(name: str):
    return {"open_loop": jaxtraffic.open_loop, "lyapunov": jaxtraffic.lyapunov,
            "constant_gains": lambda: jaxtraffic.constant_gains(*GAINS),
            "backstepping": lambda: jaxtraffic.backstepping(delay=D)}[name]()


def paper(delay: float = 0.0) -> TrafficParams:
    return TrafficParams(delay=delay)


def reference(delay: float = 0.0) -> TrafficParams:
    return TrafficParams(delay=delay, n_points=801, scheme="muscl", substeps=2)


def inputs(p: TrafficParams, batch: int):
    amps = jnp.linspace(0.005, 0.015, batch)
    rho0, v0 = jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(amps)
    return rho0, v0, jax.random.split(jax.random.PRNGKey(0), batch)


def best_of(fn, *args) -> float:
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(ARGS.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def public_call(p: TrafficParams, ctrl, steps: int):
    return jax.jit(lambda r, v, k: simulate_batch(p, ctrl, n_steps=steps, rho0=r, v0=v, keys=k,
                                                  memory=Memory()).metrics)


# ----------------------------------------------------------------------------- numpy table
def numpy_time(name: str, p: TrafficParams, rho0, v0) -> float:
    r, v = np.asarray(rho0), np.asarray(v0)
    t0 = time.perf_counter()
    numpy_ref.run_controller(name, p, r, v, ARGS.numpy_steps, gains=GAINS, delay=D)
    return (time.perf_counter() - t0) * ARGS.steps / ARGS.numpy_steps


def numpy_table() -> list[dict]:
    rows = []
    for name in ARGS.controllers.split(","):
        p = paper(D if name == "backstepping" else 0.0)
        ctrl = controller(name)
        for b in (int(x) for x in ARGS.batch_sizes.split(",")):
            rho0, v0, keys = inputs(p, b)
            fn = public_call(p, ctrl, ARGS.steps)
            jax.block_until_ready(fn(rho0, v0, keys))
            tj, tn = [], []
            for _ in range(ARGS.repeats):  # interleaved
                t0 = time.perf_counter()
                jax.block_until_ready(fn(rho0, v0, keys))
                tj.append(time.perf_counter() - t0)
                tn.append(numpy_time(name, p, rho0, v0))
            rows.append({"controller": name, "batch": b, "jax_s": min(tj), "numpy_s": min(tn),
                         "x_numpy": min(tn) / min(tj), "cell_updates_per_s": b * ARGS.steps * p.n_points / min(tj)})
            if not ARGS.json:
                print(f"  {name:14s} batch {b:5d}: {rows[-1]['x_numpy']:.1f}x numpy", file=sys.stderr)
    return rows


# ----------------------------------------------------------------------------- breakdown
def breakdown_variants(p: TrafficParams, steps: int):
    """The five programs of the breakdown, each ``f(rho0, v0, keys) -> final fields``."""
    ctrl = jaxtraffic.lyapunov()
    eq = equilibrium(p)
    alphas = jnp.full((steps,), p.alpha, jnp.float32)

    def scan_batch(step_one, init_one):
        def run(rho0, v0, keys):
            def one(r, v):
                return jax.lax.scan(step_one, init_one(r, v), alphas)[0]
            return jax.vmap(one)(rho0, v0)
        return jax.jit(run)

    def bare(c, a):
        r, v = c
        return arz_step(r, v, jnp.full_like(r, p.h_bar), p, a)[:2], None

    def with_law(c, a):
        r, v = c
        st = initial_state(p, r, v)
        h = saturate(ctrl.act(None, st.observation(p), p, None)[0], p)
        return arz_step(r, v, h, p, a)[:2], None

    def with_delay(c, a):
        st, = c
        h = saturate(ctrl.act(None, st.observation(p), p, None)[0], p)
        sent = delay_buffer.push(st.sent, h)
        r, v = arz_step(st.rho, st.v, delay_buffer.read(sent, p.delay_steps), p, a)[:2]
        return (st.replace(rho=r, v=v, sent=sent, h_prev=h, step=st.step + 1),), None

    def with_checks(c, a):
        st, = c
        new, _, _, info = closed_loop_step(st, None, ctrl, p, p, a, jax.random.PRNGKey(0), eq)
        return (new,), None

    plant = lambda r, v: (initial_state(p, r, v),)  # noqa: E731
    full = public_call(p, ctrl, steps)
    return {"bare step": scan_batch(bare, lambda r, v: (r, v)),
            "+ controller": scan_batch(with_law, lambda r, v: (r, v)),
            "+ delay line": scan_batch(with_delay, plant),
            "+ checks": scan_batch(with_checks, plant),
            "full public call": full}


def breakdown(p: TrafficParams, label: str) -> list[dict]:
    rows = []
    steps = ARGS.steps if p.n_points <= 201 else max(ARGS.steps // 4, 20)
    variants = breakdown_variants(p, steps)
    for b in (int(x) for x in ARGS.batch_sizes.split(",")):
        rho0, v0, keys = inputs(p, b)
        t = {k: best_of(f, rho0, v0, keys) for k, f in variants.items()}
        rows.append({"plant": label, "batch": b, "bare_s": t["bare step"],
                     **{k: t[k] / t["bare step"] for k in t}})
        if not ARGS.json:
            print(f"  {label} batch {b}: " + ", ".join(f"{k} {v / t['bare step']:.2f}" for k, v in t.items()),
                  file=sys.stderr)
    return rows


# ----------------------------------------------------------------------------- PPO environment
def env_rates(batch: int) -> dict:
    """Env steps/s of ``step_env`` with the reset only where done and (if this checkout has the switch,
    ``learn.env.RESET_ONLY_WHERE_DONE``) with the select of a fresh episode everywhere, timed interleaved."""
    from jaxtraffic.learn import env as learn_env

    ep = learn_env.make_env_params()
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    _, state = jax.vmap(learn_env.reset_env, (0, None))(keys, ep)
    actions = jax.random.normal(jax.random.PRNGKey(2), (ARGS.env_steps, batch, 3))

    def run(state, actions):
        def body(c, xs):
            st, k = c
            k, sub = jax.random.split(k)
            obs, st, r, done, _ = jax.vmap(learn_env.step_env, (0, 0, 0, None))(
                jax.random.split(sub, batch), st, xs, ep)
            return (st, k), r.sum() + obs.sum()  # (the observation is used, as in training)
        return jax.lax.scan(body, (state, jax.random.PRNGKey(3)), actions)

    modes = {"default": None}
    if hasattr(learn_env, "RESET_ONLY_WHERE_DONE"):
        modes = {"reset where done": True, "select everywhere": False}
    compiled, before = {}, getattr(learn_env, "RESET_ONLY_WHERE_DONE", None)
    for name, flag in modes.items():
        if flag is not None:
            learn_env.RESET_ONLY_WHERE_DONE = flag
        # a new function object per mode: jit caches traces by function, and the switch is read at trace time
        compiled[name] = jax.jit(lambda s, a: run(s, a)).lower(state, actions).compile()
    if len(modes) > 1:
        learn_env.RESET_ONLY_WHERE_DONE = before
    times = {name: [] for name in modes}
    for _ in range(ARGS.repeats):
        for name, fn in compiled.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(state, actions))
            times[name].append(time.perf_counter() - t0)
    return {name: batch * ARGS.env_steps / min(t) for name, t in times.items()}


def main() -> None:
    skip = set(filter(None, ARGS.skip.split(",")))
    out = {"info": {"jax": jax.__version__, "cpu": cpu_model(), "cpus": os.cpu_count(), "devices": len(jax.devices()),
                    "steps": ARGS.steps, "repeats": ARGS.repeats, "loadavg_start": os.getloadavg(),
                    "jaxtraffic": os.path.dirname(jaxtraffic.__file__)}}
    if "numpy" not in skip:
        out["numpy"] = numpy_table()
    if "breakdown" not in skip:
        out["breakdown"] = breakdown(paper(D), "paper")
        if ARGS.reference:
            out["breakdown"] += breakdown(reference(D), "reference")
    out["env_steps_per_s"] = {b: env_rates(int(b)) for b in filter(None, ARGS.env_batches.split(","))}
    out["info"]["loadavg_end"] = os.getloadavg()
    if ARGS.json:
        print(json.dumps(out, indent=1))
        return
    print(f"jax {out['info']['jax']}, {out['info']['cpu']}, {out['info']['devices']} device(s), load "
          f"{out['info']['loadavg_start'][0]:.1f} -> {out['info']['loadavg_end'][0]:.1f}; {out['info']['jaxtraffic']}")
    if "numpy" in out:
        bs = ARGS.batch_sizes.split(",")
        print("\n| paper grid, batch " + " / ".join(bs) + " | x batched numpy |\n|---|---|")
        for name in ARGS.controllers.split(","):
            xs = [r["x_numpy"] for r in out["numpy"] if r["controller"] == name]
            print(f"| {name} | " + " / ".join(f"{x:.1f}x" for x in xs) + " |")
    if "breakdown" in out:
        keys = ["bare step", "+ controller", "+ delay line", "+ checks", "full public call"]
        print("\n| plant | batch | " + " | ".join(keys) + " |\n|---|---:|" + "---:|" * len(keys))
        for r in out["breakdown"]:
            print(f"| {r['plant']} | {r['batch']} | " + " | ".join(f"{r[k]:.2f}" for k in keys) + " |")
    for b, rates in out["env_steps_per_s"].items():
        print(f"PPO environment, {b} envs: " + ", ".join(f"{k} {v:.3g}" for k, v in rates.items()) + " env steps/s"
              + (f" (x{rates['reset where done'] / rates['select everywhere']:.2f})" if len(rates) > 1 else ""))


if __name__ == "__main__":
    main()
