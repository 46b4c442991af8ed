#!/usr/bin/env python
"""PPO training benchmark (the training targets below), at the paper grid (201 points, dt = 0.1 s, D = 4 s).

(a) throughput: environment steps per second of ``train_chunk`` with the default network and
    the default ``train.py`` settings, for each ``--num-envs`` (compile excluded; the first chunk,
    which compiles, and the deterministic evaluation are timed separately);
(b) time to target: wall time (compile included) until the deterministic policy first reaches
    evaluation reward >= -0.1 from the paper's initial condition: runs ``python train.py`` with
    the default settings and ``--max-wall-s`` as a budget, and reads ``summary.json``
    (``seconds_to_paper_rule``: trainer wall time from before initialisation, so it includes every
    compilation but not the Python/JAX import; ``seconds_to_stop_rule``: when the default stop
    rule, which also asks for a positive closed-loop wave speed, held first; the process wall time
    is reported too);
(c) the trained policy (``load_policy``) vs the delay-compensated baseline ``backstepping(4.0)``
    (and open loop, for scale) on the nonlinear plant over 300 s: final density L2 and J_comfort.
    Targets: policy L2 below the baseline's, J_comfort within 20 % of it.

    python benchmarks/bench_train.py                      # everything (minutes)
    python benchmarks/bench_train.py --num-envs 64 256 --skip-train --policy-run /tmp/runG --json

The CPU may be shared: the load average (os.getloadavg) is recorded before and after each part.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import jax  # noqa: E402
import numpy as np  # noqa: E402
from machine import cpu_model, load  # noqa: E402  (benchmarks/machine.py)

from jaxtraffic import backstepping, open_loop, simulate  # noqa: E402
from jaxtraffic.learn import ppo  # noqa: E402
from jaxtraffic.learn.env import TrafficEnv  # noqa: E402
from jaxtraffic.runs.config import TrainConfig  # noqa: E402
from jaxtraffic.runs.policy import load_policy  # noqa: E402
from jaxtraffic.runs.ppo.trainer import build, make_evaluator  # noqa: E402

SIM_STEPS = 3000  # 300 s at dt = 0.1 s


def _block(x):
    jax.block_until_ready(x)
    return x


def throughput(num_envs: int, chunks: int) -> dict:
    """Steps/s of ``train_chunk`` with the default settings but ``num_envs``."""
    s = TrainConfig.make(ppo={"num_envs": num_envs})
    cfg, env_params = build(s)
    steps_per_chunk = cfg.steps_per_update * cfg.updates_per_chunk
    load0 = load()
    t0 = time.perf_counter()
    init, train_chunk = ppo.make_train(cfg, env_params, env=TrafficEnv)
    runner = _block(init(jax.random.PRNGKey(0)))
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    runner, m = train_chunk(runner)
    _block(m)
    t_first = time.perf_counter() - t0
    times = []
    for _ in range(chunks):
        t0 = time.perf_counter()
        runner, m = train_chunk(runner)
        _block(m)
        times.append(time.perf_counter() - t0)
    steady = float(np.median(times))
    evaluate = make_evaluator(cfg, env_params, round(s.eval_horizon_s / s.dt))
    t0 = time.perf_counter()
    evaluate(runner)
    t_eval_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    evaluate(runner)
    t_eval = time.perf_counter() - t0
    return {
        "num_envs": num_envs, "num_steps": cfg.num_steps, "updates_per_chunk": cfg.updates_per_chunk,
        "update_epochs": cfg.update_epochs, "num_minibatches": cfg.num_minibatches, "hidden": list(cfg.hidden),
        "steps_per_chunk": steps_per_chunk, "timed_chunks": chunks,
        "init_s": round(t_init, 2), "first_chunk_s": round(t_first, 2),
        "compile_s_est": round(t_first - steady, 2),  # first chunk minus a steady one
        "chunk_s_median": round(steady, 3), "chunk_s_all": [round(t, 3) for t in times],
        "steps_per_s": round(steps_per_chunk / steady), "steps_per_s_best": round(steps_per_chunk / min(times)),
        "eval_first_s": round(t_eval_first, 2), "eval_s": round(t_eval, 3),
        "load_before": load0, "load_after": load(),
    }


def time_to_target(run_dir: Path, max_wall_s: float, extra: list[str]) -> dict:
    """``python train.py`` (default settings) into ``run_dir`` with a wall budget; reads summary.json."""
    cmd = [sys.executable, str(REPO / "train.py"), "--out-dir", str(run_dir), "--max-wall-s", str(max_wall_s), *extra]
    load0 = load()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"train.py failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    summary = json.loads((run_dir / "summary.json").read_text())
    progress = [line for line in proc.stdout.splitlines() if line.startswith("[")]
    return {
        "command": " ".join(["python", "train.py", "--out-dir", str(run_dir), "--max-wall-s", str(max_wall_s),
                             *extra]),
        "run_dir": str(run_dir), "process_wall_s": round(wall, 1), **_summary_fields(summary),
        "progress_lines": len(progress), "last_progress": progress[-1] if progress else None,
        "load_before": load0, "load_after": load(),
    }


def _summary_fields(summary: dict) -> dict:
    fe = summary.get("final_eval", {})
    first = lambda k: (fe.get(k) or [None])[0]  # noqa: E731
    return {
        "seconds_to_stop_rule": summary.get("seconds_to_stop_rule"),
        "env_steps_to_stop_rule": summary.get("env_steps_to_stop_rule"),
        "seconds_to_paper_rule": summary.get("seconds_to_paper_rule"),
        "stop_rule_reached": summary.get("stop_rule_reached"), "trainer_wall_s": summary.get("wall_s"),
        "env_steps": summary.get("env_steps"), "final_eval_reward": first("final_reward"),
        "final_eval_J_comfort": first("J_comfort"),
    }


def compare(run_dir: Path) -> dict:
    """The run's deterministic policy vs backstepping(4.0) and open loop, nonlinear plant, 300 s."""
    ctrl, config = load_policy(run_dir)
    pc = config.plant
    plant = pc.replace(alpha_noise=0.0)
    out = {"run_dir": str(run_dir), "plant": {"delay": pc.delay, "alpha": pc.alpha, "n_points": pc.n_points,
                                               "dt": pc.dt},
           "horizon_s": SIM_STEPS * pc.dt, "load_before": load()}
    keys = ("final_rho_L2", "final_v_L2", "J_comfort", "J_TTT", "J_fuel", "final_reward", "diverged",
            "time_to_reward_target_s", "control_effort")
    for name, c in (("ppo", ctrl), ("backstepping", backstepping(4.0)), ("open_loop", open_loop())):
        res = simulate(plant, c, n_steps=SIM_STEPS)
        out[name] = {k: _num(res.metrics[k]) for k in keys}
    ppo_row, bs_row = out["ppo"], out["backstepping"]
    out["rho_L2_ratio"] = ppo_row["final_rho_L2"] / bs_row["final_rho_L2"]
    out["J_comfort_ratio"] = ppo_row["J_comfort"] / bs_row["J_comfort"]
    out["target_L2_below_baseline"] = bool(ppo_row["final_rho_L2"] < bs_row["final_rho_L2"])
    out["target_J_comfort_within_20pct"] = bool(abs(out["J_comfort_ratio"] - 1.0) <= 0.2)
    out["load_after"] = load()
    return out


def _num(x):
    v = np.asarray(x).item()
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return v


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[64, 256], help="(a) batch sizes")
    parser.add_argument("--chunks", type=int, default=3, help="(a) timed chunks after the compiling one")
    parser.add_argument("--max-wall-s", type=float, default=600.0, help="(b) wall budget of the training run")
    parser.add_argument("--train-dir", default=None, help="(b) run directory (default: a fresh temporary one)")
    parser.add_argument("--train-args", default="", help="(b) extra train.py flags (default: none, the defaults)")
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--skip-train", action="store_true", help="skip (b); (c) then needs --policy-run")
    parser.add_argument("--policy-run", default=None, help="(c) run directory to evaluate (default: the run of (b))")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    args = parser.parse_args(argv)

    res: dict = {"machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "jax": jax.__version__,
                             "devices": [str(d) for d in jax.devices()], "python": platform.python_version()},
                 "load_start": load()}
    say = (lambda *a: None) if args.json else (lambda *a: print(*a, flush=True))
    say(f"machine: {res['machine']['cpu']}, {res['machine']['cores']} cores, jax {jax.__version__}, "
        f"load {res['load_start']}")
    if not args.skip_throughput:
        res["throughput"] = []
        for n in args.num_envs:
            t = throughput(n, args.chunks)
            res["throughput"].append(t)
            say(f"(a) num_envs={n:4d}: {t['steps_per_s']:8d} env steps/s (median of {t['timed_chunks']} chunks of "
                f"{t['steps_per_chunk']} steps, {t['chunk_s_median']} s each; best {t['steps_per_s_best']}); "
                f"init {t['init_s']} s, first chunk {t['first_chunk_s']} s (compile ~{t['compile_s_est']} s); "
                f"300 s evaluation {t['eval_s']} s (first {t['eval_first_s']} s); load {t['load_before']} -> "
                f"{t['load_after']}")
    run_dir = Path(args.policy_run) if args.policy_run else None
    if not args.skip_train:
        train_dir = Path(args.train_dir or tempfile.mkdtemp(prefix="bench_train_"))
        t = time_to_target(train_dir, args.max_wall_s, args.train_args.split())
        res["time_to_target"] = t
        fmt = lambda s: f"{s:.1f} s" if s is not None else "NOT within the budget"  # noqa: E731
        say(f"(b) {t['command']}: eval reward >= -0.1 (the paper's rule) first met after "
            f"{fmt(t['seconds_to_paper_rule'])}; the full stop rule (with the wave speed) after "
            f"{fmt(t['seconds_to_stop_rule'])} (env steps {t['env_steps_to_stop_rule']});"
            f" trainer wall {t['trainer_wall_s']:.1f} s, process {t['process_wall_s']} s, final eval reward "
            f"{t['final_eval_reward']:.4f}; load {t['load_before']} -> {t['load_after']}")
        run_dir = run_dir or train_dir
    if run_dir is not None:
        if not (run_dir / "summary.json").exists():
            raise SystemExit(f"{run_dir} has no summary.json (training not finished?)")
        c = compare(run_dir)
        c["summary"] = _summary_fields(json.loads((run_dir / "summary.json").read_text()))
        res["compare"] = c
        for name in ("ppo", "backstepping", "open_loop"):
            m = c[name]
            say(f"(c) {name:12s}: final rho L2 {m['final_rho_L2']:.4g} veh/km, J_comfort {m['J_comfort']:.1f}, "
                f"final reward {m['final_reward']:.4f}, diverged {m['diverged']}")
        say(f"(c) ppo/backstepping: L2 ratio {c['rho_L2_ratio']:.3f} (target < 1: "
            f"{c['target_L2_below_baseline']}), J_comfort ratio {c['J_comfort_ratio']:.3f} (target within 20 %: "
            f"{c['target_J_comfort_within_20pct']}); policy from {run_dir}")
    res["load_end"] = load()
    if args.json:
        print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
