"""Simulator throughput at the paper's grid (201 points, dt = 0.1 s), float32.

For each controller (open loop, Lyapunov) and batch size, one jit-compiled batched rollout
(``jaxtraffic.simulate_batch``, streaming metrics, no trajectory) is compiled once (timed
separately: trace + lower + compile) and then timed over ``--repeats`` calls (best and median).

    env steps/s   = batch * steps / seconds
    cell updates/s = env steps/s * 201

Also measured: the compile time of a 3000-step single-environment rollout (``simulate``), and,
in a fresh subprocess, the peak resident memory (VmHWM) of a batch of 4096 environments over
300 s (3000 steps) with the Lyapunov controller, without trajectories.

Devices: by default the host is split into one XLA CPU device per core (``jaxtraffic.split_host_devices``,
what the command lines do) and ``simulate_batch`` shards the batch over them. ``--devices N`` sets
``--xla_force_host_platform_device_count=N`` instead (1: one device, what ``import jaxtraffic`` alone
gives a program; ``benchmarks/bench_device_split.py`` compares the two).

Ratio to numpy: every row also times the same closed loop (Lyapunov law + upwind ARZ step) written
as plain batched numpy (``benchmarks/numpy_ref.py``) at the same batch size, in the same process,
interleaved with the JAX calls, and prints jax / numpy (best of each), a figure that survives a
noisy machine better than either throughput alone. ``--numpy-steps`` sets its (shorter) rollout.

Limit: the estimated per-core limit for this step (``FLOPS_PER_CELL`` vector operations per cell
update, counted in numpy_ref, on 2 vector ALUs x SIMD lanes x clock; divisions are pipelined on
their own unit and are not the bound), and the fraction of (limit x cores) reached.

Usage:
    python benchmarks/bench_sim.py                 # table
    python benchmarks/bench_sim.py --json          # machine-readable
    python benchmarks/bench_sim.py --batch-sizes 1,64 --steps 300 --repeats 3 --no-memory
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

N_POINTS = 201


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch-sizes", default="1,64,1024,4096", help="comma-separated batch sizes")
    ap.add_argument("--steps", type=int, default=600, help="steps per timed rollout (dt = 0.1 s)")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls per configuration")
    ap.add_argument("--controllers", default="open_loop,lyapunov", help="open_loop and/or lyapunov")
    ap.add_argument("--devices", type=int, default=0,
                    help="force N XLA host devices (default 0: one per core, as the command lines split)")
    ap.add_argument("--numpy-steps", type=int, default=100, help="steps of each timed numpy rollout")
    ap.add_argument("--chunk-size", type=lambda s: s if s == "auto" else int(s), default="auto",
                    help="simulate_batch chunk_size (environments per sequential chunk; 0: one vmap; "
                         "auto: 64 on a CPU, one vmap on an accelerator)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    ap.add_argument("--no-memory", action="store_true", help="skip the 4096-env memory measurement")
    ap.add_argument("--memory-batch", type=int, default=4096)
    ap.add_argument("--memory-steps", type=int, default=3000)
    ap.add_argument("--_memory-child", action="store_true", help=argparse.SUPPRESS)
    return ap.parse_args()


ARGS = _parse()
if ARGS.devices:
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={ARGS.devices}")
if not ARGS.devices:
    from jaxtraffic import split_host_devices

    split_host_devices()  # one device per core, before jax starts

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import numpy_ref  # noqa: E402  (benchmarks/numpy_ref.py)
from machine import cpu_ghz, cpu_model, simd_lanes_f32  # noqa: E402  (benchmarks/machine.py)

import jaxtraffic  # noqa: E402
from jaxtraffic import Memory, TrafficParams, paper_initial_condition, simulate, simulate_batch  # noqa: E402

CONTROLLERS = {"open_loop": jaxtraffic.open_loop, "lyapunov": jaxtraffic.lyapunov}


def _batch_inputs(batch: int, p: TrafficParams):
    """Batched initial states (paper IC with amplitudes 5..15 veh/km) and keys."""
    amps = jnp.linspace(0.005, 0.015, batch)
    rho0, v0 = jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(amps)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    return rho0, v0, keys


# vector operations per cell update of the closed loop (numpy_ref.make_step: Lyapunov law 9,
# upwind step 24, of which 2 divisions); the simulator also accumulates the metrics (~15 more)
FLOPS_PER_CELL = 33
BYTES_PER_CELL = 16  # rho and v read and written once (in cache); the delay buffer adds 8 when D > 0


def core_limit() -> dict:
    """Estimated cell updates/s per core: 2 vector ALUs x lanes x clock / FLOPS_PER_CELL."""
    lanes, ghz = simd_lanes_f32(), cpu_ghz()
    ops = 2 * lanes * ghz * 1e9
    return {"simd_lanes_f32": lanes, "ghz": ghz, "vector_ops_per_s": ops, "flops_per_cell": FLOPS_PER_CELL,
            "bytes_per_cell": BYTES_PER_CELL, "cell_updates_per_s_per_core": ops / FLOPS_PER_CELL}


def _numpy_time(batch: int, steps: int) -> float:
    p = TrafficParams()
    rho0, v0, _ = _batch_inputs(batch, p)
    rho0, v0 = np.asarray(rho0), np.asarray(v0)
    t0, c0 = time.perf_counter(), time.process_time()
    numpy_ref.run(p, rho0, v0, steps)
    return time.perf_counter() - t0, time.process_time() - c0


def _timed(fn, *args, repeats: int) -> tuple[list[float], list[float]]:
    """Wall-clock and process CPU seconds (all threads) of ``repeats`` calls."""
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return times, cpu


def bench_throughput(controller_name: str, batch: int, steps: int, repeats: int) -> dict:
    p = TrafficParams()
    ctrl = CONTROLLERS[controller_name]()
    rho0, v0, keys = _batch_inputs(batch, p)

    def run(rho0, v0, keys):
        return simulate_batch(p, ctrl, n_steps=steps, rho0=rho0, v0=v0, keys=keys,
                              memory=Memory(chunk_size=ARGS.chunk_size)).metrics

    t0 = time.perf_counter()
    compiled = jax.jit(run).lower(rho0, v0, keys).compile()
    compile_s = time.perf_counter() - t0
    times, cpu, np_times, np_cpu = [], [], [], []
    for _ in range(repeats):  # interleaved, so that both see the same machine
        t, c = _timed(compiled, rho0, v0, keys, repeats=1)
        times += t
        cpu += c
        t_np, c_np = (x * steps / ARGS.numpy_steps for x in _numpy_time(batch, ARGS.numpy_steps))
        np_times.append(t_np)
        np_cpu.append(c_np)
    best, med = min(times), statistics.median(times)
    env_steps = batch * steps
    limit = core_limit()["cell_updates_per_s_per_core"] * len(os.sched_getaffinity(0))
    return {
        "controller": controller_name, "batch": batch, "steps": steps, "compile_s": compile_s,
        "best_s": best, "median_s": med, "env_steps_per_s": env_steps / best,
        "cell_updates_per_s": env_steps * N_POINTS / best,
        "cell_updates_per_s_median": env_steps * N_POINTS / med,
        # efficiency per core: cell updates per second of process CPU time (insensitive to other
        # processes taking turns on the cores; wall-clock figures above are what a user sees)
        "cell_updates_per_cpu_s": env_steps * N_POINTS / min(cpu),
        "numpy_cell_updates_per_s": env_steps * N_POINTS / min(np_times),
        "ratio_vs_numpy": min(np_times) / best,
        # per CPU-second (both): what each busy core does; x cores = the ratio on an idle machine
        "ratio_vs_numpy_per_cpu_s": min(np_cpu) / min(cpu), "fraction_of_limit": env_steps * N_POINTS / best / limit,
        "loadavg": os.getloadavg()[0],
    }


def bench_compile_3000() -> dict:
    """Compile time of a single 3000-step rollout: first call minus a warm call."""
    p = TrafficParams()
    rho0, v0 = paper_initial_condition(p)
    out = {}
    for name in ("open_loop", "lyapunov"):
        ctrl = CONTROLLERS[name]()
        jax.clear_caches()
        t0 = time.perf_counter()
        jax.block_until_ready(simulate(p, ctrl, n_steps=3000, rho0=rho0, v0=v0).metrics)
        first = time.perf_counter() - t0
        warm = min(_timed(lambda c=ctrl: simulate(p, c, n_steps=3000, rho0=rho0, v0=v0).metrics, repeats=3)[0])
        out[name] = {"first_call_s": first, "warm_call_s": warm, "compile_s": first - warm}
    return out


def _peak_rss_mib() -> float:
    """Peak resident set size of this process in MiB: VmHWM (reset by exec, unlike ru_maxrss,
    which a child started by a large parent inherits), else ru_maxrss."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def memory_child(batch: int, steps: int) -> dict:
    """Run once (in a fresh process) and report the peak resident set size."""
    rss0 = _peak_rss_mib()
    p = TrafficParams()
    rho0, v0, keys = _batch_inputs(batch, p)
    t0 = time.perf_counter()
    m = simulate_batch(p, jaxtraffic.lyapunov(), n_steps=steps, rho0=rho0, v0=v0, keys=keys,
                       memory=Memory(chunk_size=ARGS.chunk_size)).metrics
    jax.block_until_ready(m)
    wall = time.perf_counter() - t0
    peak = _peak_rss_mib()
    return {"batch": batch, "steps": steps, "controller": "lyapunov", "peak_rss_MiB": peak,
            "rss_before_MiB": rss0, "wall_incl_compile_s": wall,
            "diverged": int(np.sum(np.asarray(m["diverged"])))}


def bench_memory() -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--_memory-child", "--memory-batch",
           str(ARGS.memory_batch), "--memory-steps", str(ARGS.memory_steps), "--devices", str(ARGS.devices),
           "--chunk-size", str(ARGS.chunk_size)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    if ARGS._memory_child:
        print(json.dumps(memory_child(ARGS.memory_batch, ARGS.memory_steps)))
        return
    info = {
        "jax": jax.__version__, "jaxtraffic": jaxtraffic.__version__, "cpu": cpu_model(),
        "cpu_count": os.cpu_count(), "devices": len(jax.devices()), "backend": jax.default_backend(),
        "dtype": "float32", "n_points": N_POINTS, "dt_s": 0.1, "chunk_size": ARGS.chunk_size,
        "loadavg_at_start": os.getloadavg(), "nice": os.nice(0), "limit": core_limit(),
    }
    memory = None if ARGS.no_memory else bench_memory()  # first, while this process is small
    rows = []
    for name in ARGS.controllers.split(","):
        for b in (int(x) for x in ARGS.batch_sizes.split(",")):
            rows.append(bench_throughput(name, b, ARGS.steps, ARGS.repeats))
            if not ARGS.json:
                r = rows[-1]
                print(f"  {name:9s} batch {b:5d}: {r['cell_updates_per_s']:.3g} cell updates/s,"
                      f" {r['ratio_vs_numpy']:.1f}x numpy", file=sys.stderr)
    result = {"info": info, "throughput": rows, "compile_3000_steps": bench_compile_3000()}
    if memory is not None:
        result["memory"] = memory
    result["info"]["loadavg_at_end"] = os.getloadavg()
    if ARGS.json:
        print(json.dumps(result, indent=2))
        return
    print(f"jax {info['jax']} on {info['cpu']} ({info['cpu_count']} CPUs, {info['devices']} XLA device(s)),"
          f" float32, {N_POINTS} points, dt 0.1 s, {ARGS.steps} steps per rollout, best of {ARGS.repeats},"
          f" chunk_size {ARGS.chunk_size}")
    print(f"load average at start / end: {info['loadavg_at_start']} / {result['info']['loadavg_at_end']}")
    print()
    lim = info["limit"]
    print(f"estimated limit: {lim['flops_per_cell']} vector ops and {lim['bytes_per_cell']} B per cell update;"
          f" {lim['simd_lanes_f32']} float32 lanes x 2 ALUs x {lim['ghz']:.2f} GHz ="
          f" {lim['cell_updates_per_s_per_core']:.3g} cell updates/s per core")
    print()
    print("| controller | batch | env steps/s | cell updates/s (best) | cell updates/s (median)"
          " | cell updates per CPU-s | numpy cell updates/s | x numpy | x numpy per CPU-s | of limit | load"
          " | compile s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['controller']} | {r['batch']} | {r['env_steps_per_s']:.3g} | {r['cell_updates_per_s']:.3g}"
              f" | {r['cell_updates_per_s_median']:.3g} | {r['cell_updates_per_cpu_s']:.3g}"
              f" | {r['numpy_cell_updates_per_s']:.3g} | {r['ratio_vs_numpy']:.1f}"
              f" | {r['ratio_vs_numpy_per_cpu_s']:.1f} | {r['fraction_of_limit']:.0%}"
              f" | {r['loadavg']:.1f} | {r['compile_s']:.2f} |")
    print()
    for name, c in result["compile_3000_steps"].items():
        print(f"compile of a 3000-step rollout ({name}): {c['compile_s']:.2f} s"
              f" (first call {c['first_call_s']:.2f} s, warm call {c['warm_call_s']:.3f} s)")
    if "memory" in result:
        m = result["memory"]
        print(f"peak RSS, {m['batch']} envs x {m['steps']} steps ({m['controller']}, no trajectory):"
              f" {m['peak_rss_MiB']:.0f} MiB (before the run {m['rss_before_MiB']:.0f} MiB)")


if __name__ == "__main__":
    main()
