"""The anchor of the simulator's speed (issue 48.2): jaxtraffic's default closed loop as a hand-written C kernel
(``benchmarks/c_ref/arz_step.c``), built here with the system compiler (``cc -O3 -march=native``; ``$CC``
overrides) and called through ctypes. Skipped, with a message, when no compiler is found; never a dependency
of the package.

The case is ``bench_metrics.py``'s: Lyapunov (k = 1) at D = 4 s on the paper grid (201 points, upwind, dt =
0.1 s), the ring-buffer delay line, the divergence checks and every running sum of the default call. The
script first checks the kernel: its final state and metrics against ``simulate_batch`` on the same case
(the largest relative difference of each; float32 rounding differs, the results must agree to ``--rtol``).
Then it times, interleaved in one process (best of ``--repeats``, CPU time of the process per cell update):
the C kernel with and without the metrics, jaxtraffic's default call (every metric) and its metric-free call
(``metrics=()``), and prints the two ratios issue 48 sets targets for (default / metric-free <= 1.5,
metric-free / C metric-free <= 1.5). XLA runs on one device and one thread (``--xla_cpu_multi_thread_eigen=
false intra_op_parallelism_threads=1``, set before jax starts), like the single-threaded C kernel.

    python benchmarks/c_kernel.py                        # batch 1024, 300 steps
    python benchmarks/c_kernel.py --batch 64 --steps 100 --repeats 2 --json
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from machine import cpu_model, load  # noqa: E402  (benchmarks/machine.py)

from jaxtraffic import TrafficParams, lyapunov, paper_initial_condition, simulate_batch  # noqa: E402
from jaxtraffic.model.linear import linearize  # noqa: E402
from jaxtraffic.sim.rollout import plant_alphas  # noqa: E402

SOURCE = Path(__file__).parent / "c_ref" / "arz_step.c"
D = 4.0  # s, the plant's delay (bench_metrics.py's case)
GAIN, KEEP = 1.0, 0.0  # the Lyapunov law's gain k and kept share (lyapunov()'s defaults)
N_SUMS, N_INTS = 10, 5  # the kernel's running sums per node and counters (arz_step.c's enums)
SUMS = ("J_TTT", "J_fuel", "J_comfort", "effort", "max_cfl", "a_prev", "a2", "at2", "switch", "fuel_kmh")
KMH2 = 3.6 * 3.6


def build(out_dir: Path) -> ctypes.CDLL | None:
    """The kernel compiled into ``out_dir`` and loaded, or None (with the reason printed) without a compiler."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        print("c_kernel: no C compiler found (cc, gcc, clang or $CC): the C reference is skipped")
        return None
    lib = out_dir / "libarz_step.so"
    cmd = [cc, "-O3", "-march=native", "-fopenmp-simd", "-shared", "-fPIC", str(SOURCE), "-o", str(lib), "-lm"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode:
        print(f"c_kernel: {' '.join(cmd)} failed, the C reference is skipped:\n{done.stderr[-2000:]}")
        return None
    dll = ctypes.CDLL(str(lib))
    f32, i32 = np.ctypeslib.ndpointer(np.float32, flags="C"), np.ctypeslib.ndpointer(np.int32, flags="C")
    dll.arz_closed_loop.argtypes = [ctypes.c_int] * 6 + [f32, f32, f32, f32, ctypes.c_void_p, i32]
    dll.arz_closed_loop.restype = ctypes.c_int
    return dll


def constants(p: TrafficParams) -> np.ndarray:
    """The kernel's constants (arz_step.c's enum order), float32, from jaxtraffic's own functions."""
    lm = linearize(p)
    vals = (lm.rho_bar, lm.v_bar, p.h_bar, lm.V_rho, lm.V_h, GAIN, KEEP, p.h_min, p.h_max, p.q_in, p.l, p.dt,
            p.dx, p.tau_acc, p.tau_m, p.h_m)
    return np.array([np.float32(jnp.asarray(x, jnp.float32)) for x in vals], np.float32)


def run_c(dll: ctypes.CDLL, p: TrafficParams, rho0, v0, alphas, n_steps: int, with_metrics: bool):
    """(rho, v, sums (B, N_SUMS, n) or None, ints (B, N_INTS)) after ``n_steps`` steps of the kernel."""
    b, n = rho0.shape
    rho, v = np.array(rho0, np.float32, order="C"), np.array(v0, np.float32, order="C")
    sums = np.zeros((b, N_SUMS, n), np.float32) if with_metrics else None
    ints = np.zeros((b, N_INTS), np.int32)
    rc = dll.arz_closed_loop(b, n, n_steps, p.delay_steps, p.max_delay_steps + 1, p.delay_steps, constants(p),
                             np.ascontiguousarray(alphas, np.float32), rho, v,
                             None if sums is None else sums.ctypes.data, ints)
    if rc:
        raise MemoryError("arz_closed_loop could not allocate its scratch")
    return rho, v, sums, ints


def c_metrics(p: TrafficParams, rho, v, sums, ints, n_steps: int) -> dict[str, np.ndarray]:
    """The default call's indices from the kernel's sums (sim.metrics' definitions, float64 here)."""
    lm = linearize(p)
    rb, vb, dx, dt = float(lm.rho_bar), float(lm.v_bar), float(p.dx), float(p.dt)
    s = {k: sums[:, i].astype(np.float64) for i, k in enumerate(SUMS)}

    def trap(f):
        return dx * (f.sum(-1) - 0.5 * (f[:, 0] + f[:, -1]))

    r_fin = -(((rho - rb) / rb) ** 2 + ((v - vb) / vb) ** 2).sum(-1) * (dx / 5.0)
    n_active, last_bad, diverged = ints[:, 0], ints[:, 1], ints[:, 2].astype(bool)
    reached = ~diverged & (last_bad < n_steps - 1) & (r_fin >= -0.1)
    a2, at2, sw = trap(s["a2"]), trap(s["at2"]), trap(s["switch"])
    return {
        "J_TTT": trap(s["J_TTT"]), "J_fuel": trap(s["J_fuel"]), "J_comfort": trap(s["J_comfort"]),
        "final_rho_L2": 1e3 * np.sqrt(((rho - rb) ** 2).mean(-1)),  # veh/km, as the library reports it
        "final_v_L2": np.sqrt(((v - vb) ** 2).mean(-1)),
        "final_reward": r_fin, "time_to_reward_target_s": np.where(reached, (last_bad + 1) * dt, np.inf),
        "diverged": diverged, "diverged_reason": ints[:, 4],
        "control_effort": np.sqrt(s["effort"].mean(-1) / np.maximum(n_active, 1)),
        "max_cfl": s["max_cfl"].max(-1), "J_comfort_a2": a2, "J_comfort_at2": at2, "J_comfort_switch_on": sw,
        "J_comfort_no_switch_on": a2 + at2 - sw, "J_fuel_kmh": trap(s["fuel_kmh"]),
        "J_comfort_kmh": KMH2 * (a2 + at2), "J_comfort_no_switch_on_kmh": KMH2 * (a2 + at2 - sw),
    }


def rel_diff(a, b) -> float:
    """Largest |a - b| / max(|b|, tiny) over the batch (0 where both are equal, infinities included)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    with np.errstate(invalid="ignore"):  # inf - inf where both are inf: masked by ``same``
        d = np.where(same, 0.0, np.abs(a - b) / np.maximum(np.abs(b), 1e-30))
    return float(np.max(d))


def setup(batch: int, steps: int):
    """The case: parameters, initial states (the paper's, amplitudes 0.005-0.015), keys, alphas, controller."""
    p = TrafficParams(delay=D)
    rho0, v0 = jax.vmap(lambda a: paper_initial_condition(p, amplitude=a))(jnp.linspace(0.005, 0.015, batch))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    alphas = np.asarray(jax.vmap(lambda k: plant_alphas(p, k, steps))(keys))
    return p, np.asarray(rho0), np.asarray(v0), keys, alphas, lyapunov(k=GAIN, keep=KEEP)


def check(dll, batch: int, steps: int) -> dict[str, float]:
    """Largest relative difference, C kernel against ``simulate_batch``, of the final state and each metric."""
    p, rho0, v0, keys, alphas, ctrl = setup(batch, steps)
    res = simulate_batch(p, ctrl, n_steps=steps, rho0=rho0, v0=v0, keys=keys)
    rho, v, sums, ints = run_c(dll, p, rho0, v0, alphas, steps, True)
    out = {"final rho": rel_diff(rho, res.final.rho), "final v": rel_diff(v, res.final.v)}
    for k, val in c_metrics(p, rho, v, sums, ints, steps).items():
        out[k] = rel_diff(val, res.metrics[k])
    return out


def timings(dll, batch: int, steps: int, repeats: int) -> dict[str, float]:
    """CPU ns per cell update (best of ``repeats``, interleaved) of the four loops."""
    p, rho0, v0, keys, alphas, ctrl = setup(batch, steps)
    r0, u0 = jnp.asarray(rho0), jnp.asarray(v0)

    def xla(names):
        fn = jax.jit(lambda r, v, k: simulate_batch(p, ctrl, n_steps=steps, rho0=r, v0=v, keys=k, metrics=names))
        return lambda: jax.block_until_ready(fn(r0, u0, keys))

    calls = {"C kernel, all metrics": lambda: run_c(dll, p, rho0, v0, alphas, steps, True),
             "C kernel, no metrics": lambda: run_c(dll, p, rho0, v0, alphas, steps, False),
             "XLA default call": xla(None), "XLA metric-free call": xla(())}
    if dll is None:
        calls = {k: f for k, f in calls.items() if k.startswith("XLA")}
    for f in calls.values():
        f()  # compile, warm the caches
    best = dict.fromkeys(calls, float("inf"))
    for _ in range(repeats):
        for k, f in calls.items():
            c0 = time.process_time()
            f()
            best[k] = min(best[k], time.process_time() - c0)
    return {k: 1e9 * c / (batch * steps * p.n_points) for k, c in best.items()}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--check-batch", type=int, default=64, help="environments of the correctness check")
    ap.add_argument("--rtol", type=float, default=1e-4, help="largest relative difference the check accepts")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out: dict = {"machine": cpu_model(), "load_before": load(), "batch": args.batch, "steps": args.steps,
                 "case": f"lyapunov, D = {D:g} s, paper grid", "xla_flags": os.environ["XLA_FLAGS"].strip()}
    with tempfile.TemporaryDirectory() as tmp:
        dll = build(Path(tmp))
        if dll is not None:
            out["check"] = check(dll, args.check_batch, args.steps)
            out["check_ok"] = max(out["check"].values()) <= args.rtol
        out["cpu_ns_per_cell_update"] = t = timings(dll, args.batch, args.steps, args.repeats)
    out["default_over_metric_free"] = t["XLA default call"] / t["XLA metric-free call"]
    if dll is not None:
        out["metric_free_over_c"] = t["XLA metric-free call"] / t["C kernel, no metrics"]
        out["default_over_c_all_metrics"] = t["XLA default call"] / t["C kernel, all metrics"]
    out["load_after"] = load()
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        _report(out, args.rtol)
    if dll is not None and not out["check_ok"]:
        raise SystemExit(f"c_kernel: the C kernel disagrees with simulate_batch beyond rtol {args.rtol:g}")
    return out


def _report(out: dict, rtol: float) -> None:
    print(f"{out['machine']}; {out['case']}; batch {out['batch']}, {out['steps']} steps; "
          f"load {out['load_before']} -> {out['load_after']}; XLA_FLAGS {out['xla_flags']}")
    if "check" in out:
        worst = max(out["check"], key=out["check"].get)
        print(f"check against simulate_batch: largest relative difference {out['check'][worst]:.2e} ({worst}); "
              f"{'ok' if out['check_ok'] else 'FAILED'} at rtol {rtol:g}")
        print("  " + ", ".join(f"{k} {v:.1e}" for k, v in out["check"].items()))
    for k, v in out["cpu_ns_per_cell_update"].items():
        print(f"  {k:<24s} {v:6.2f} ns CPU per cell update")
    print(f"default / metric-free (target <= 1.5): {out['default_over_metric_free']:.2f}")
    if "metric_free_over_c" in out:
        print(f"metric-free / C metric-free (target <= 1.5): {out['metric_free_over_c']:.2f}; "
              f"default / C with all metrics: {out['default_over_c_all_metrics']:.2f}")


if __name__ == "__main__":
    main()
