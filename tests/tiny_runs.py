"""The one tiny training session of the test suite, shared by ``test_train.py`` and ``test_evaluate.py``.

A tiny problem (21 nodes, 4 environments x 8 steps, 2 updates per chunk). ``conftest.py`` starts it
once per session, in the background as soon as the tests are collected (so that it overlaps with the
unit tests that run before it), in two subprocesses: ``train_runs`` (one CPU device) and
``TWO_DEVICES`` (two forced host devices). Both compile with the test flags of ``xla_flags.py``
(cheaper compilation; every comparison in the tests is between runs of the same process).
In ``train_runs`` every run has the same PPO config and environment, so ``ppo.make_train`` is
memoised (``SharedCompile``): the trainer's own code (init, chunks, evaluation, checkpoints, resume)
runs unchanged, only the recompilation of an identical program per ``train()`` call is saved. The
tests then read the run directories; run ``A`` is also the policy that ``test_evaluate.py``
evaluates end to end (as soon as ``A`` is written, while the other runs train).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from xla_flags import with_test_flags

from jaxtraffic.cli import train as train_cli
from jaxtraffic.control import Observation
from jaxtraffic.control.gain_policy import policy_controller
from jaxtraffic.learn.ppo import algorithm as ppo
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.gradient.trainer import train_gradient
from jaxtraffic.runs.policy import load_policy
from jaxtraffic.runs.ppo.trainer import build
from jaxtraffic.sim import initial_state, paper_initial_condition

REPO = Path(__file__).resolve().parents[1]
# one member (the default is a population of 2): these runs are counted per member below;
# the population itself: test_train.test_population_run
TINY = ["--num-seeds", "1", "--n-points", "21", "--delay", "0.5", "--max-delay-steps", "20", "--num-envs", "4",
        "--num-steps", "8",
        "--updates-per-chunk", "2", "--update-epochs", "2", "--num-minibatches", "2", "--horizon-s", "3",
        "--eval-horizon-s", "2", "--val-horizon-s", "2", "--quiet"]
CHUNK = 4 * 8 * 2  # env steps per chunk
RUNS = ("A", "B", "I", "C", "S", "W", "R", "R_half")
DONE = "done.json"  # written last: the session is complete
FAILED = "failed.txt"  # written instead when the training failed (for the test processes that only wait)
GRADIENT_ROOT = "runs"  # root/runs/gradient-gains: the tiny gradient-trained run (evaluate.py --runs-root)


class SharedCompile:
    """Memoised ``make_train`` (by config, env params, devices, env); records the last runner a
    chunk returned and can raise KeyboardInterrupt at a given chunk call (a simulated Ctrl-C)."""

    def __init__(self, orig):
        self.orig, self.cache, self.last_runner, self.interrupt_at, self.calls = orig, {}, None, None, 0

    def __call__(self, cfg, env_params, devices=None, *, env):
        key = (cfg, env_params, None if devices is None else tuple(devices), env)
        if key not in self.cache:
            self.cache[key] = self.orig(cfg, env_params, devices, env=env)
        init, chunk = self.cache[key]

        def train_chunk(runner):
            self.calls += 1
            if self.interrupt_at is not None and self.calls == self.interrupt_at:
                raise KeyboardInterrupt
            runner, metrics = chunk(runner)
            self.last_runner = runner
            return runner, metrics

        return init, train_chunk


def _cli(out: Path, *extra: str) -> Path:
    return train_cli.main(TINY + ["--out-dir", str(out), *extra])


def train_runs(root: Path) -> None:
    """All the single-device runs (4 chunks = 256 env steps unless noted), in a subprocess:
    A: one go; B: 2 chunks, then --resume to 4; I: Ctrl-C before chunk 3, then --resume;
    C: seed 1, 1 chunk; S: the paper's rule alone (--min-wave-speed=-inf, no validation target), always
    met (target -1e9), patience 2, no --keep-going;
    W: like S, but the rule also asks for a wave speed no policy has (--min-wave-speed 1e9);
    R: a rule never met, random restarts every 2 chunks, 6 chunks; R_half: R's first 3 chunks, then --resume.
    Also compares, right after A, the in-memory policy with ``load_policy(A)``, and trains the tiny
    gradient runs under ``GRADIENT_ROOT`` (gains, robust schedule, residual) that test_evaluate.py evaluates
    beside A."""
    shared = SharedCompile(ppo.make_train)
    ppo.make_train = shared
    a = _cli(root / "A", "--total-steps", str(4 * CHUNK), "--keep-going")
    write_json(root / "roundtrip.json", _round_trip(a, jax.device_get(shared.last_runner)))
    # a tiny gradient-trained gains run where evaluate.py looks for it (the other gradient runs are absent)
    grad_run = {"algo": "gradient", "eval_horizon_s": 6.0, "quiet": True}
    tiny = {"train_horizon_s": 6.0, "steps_per_chunk": 1, "grad_steps": 1}
    train_gradient(TrainConfig.make(run={**grad_run, "out_dir": str(root / GRADIENT_ROOT / "gradient-gains")},
                                    plant={"n_points": 21}, grad={**tiny, "train_delays": (4.0,)}))
    # and a tiny robust delay schedule (CEM, 2 candidates x 2 plants), evaluated as grad_robust
    cem = {**tiny, "train_delays": (2.0, 6.0), "train_alphas": (0.15,), "cem_population": 2}
    train_gradient(TrainConfig.make(run={**grad_run, "out_dir": str(root / GRADIENT_ROOT / "gradient-robust")},
                                    plant={"n_points": 21}, grad={**cem, "policy": "schedule"}))
    # and a tiny learned residual on adaptive backstepping (CEM, 2 candidates x 2 plants), evaluated as grad_residual
    train_gradient(TrainConfig.make(run={**grad_run, "out_dir": str(root / GRADIENT_ROOT / "adaptive-residual")},
                                    plant={"n_points": 21}, grad={**cem, "policy": "residual"}))
    (root / "A.done").touch()  # run A (and the gradient run) complete: test_evaluate.py can start
    b = _cli(root / "B", "--total-steps", str(2 * CHUNK), "--keep-going")
    shutil.copytree(b, root / "B_first")
    train_cli.main(["--out-dir", str(b), "--resume", "--total-steps", str(4 * CHUNK), "--keep-going", "--quiet"])
    shared.calls, shared.interrupt_at = 0, 3
    try:
        _cli(root / "I", "--total-steps", str(4 * CHUNK), "--keep-going")
        raise AssertionError("the interrupted run did not exit")
    except SystemExit as exc:
        assert exc.code == 130, exc.code  # the convention for SIGINT / Ctrl-C
    i = root / "I"
    shared.interrupt_at = None
    shutil.copytree(i, root / "I_first")
    train_cli.main(["--out-dir", str(i), "--resume", "--total-steps", str(4 * CHUNK), "--keep-going", "--quiet"])
    _cli(root / "C", "--seed", "1", "--total-steps", str(CHUNK), "--keep-going")
    _cli(root / "S", "--total-steps", str(6 * CHUNK), "--target-reward=-1e9", "--min-wave-speed=-inf",
         "--val-target", "inf", "--stop-patience", "2")
    _cli(root / "W", "--total-steps", str(3 * CHUNK), "--target-reward=-1e9", "--min-wave-speed", "1e9")
    # R: random restarts every 2 chunks (the rule is never met); R_half: its first 3 chunks, then --resume
    restart = ["--target-reward=1e9", "--restart-steps", str(2 * CHUNK)]
    _cli(root / "R", "--total-steps", str(6 * CHUNK), *restart)
    _cli(root / "R_half", "--total-steps", str(3 * CHUNK), *restart)
    train_cli.main(["--out-dir", str(root / "R_half"), "--resume", "--total-steps", str(6 * CHUNK), "--quiet"])
    write_json(root / DONE, {"compiled_programs": len(shared.cache)})


def write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj))


def _round_trip(run: Path, runner) -> dict:
    """Actions of ``load_policy(run, checkpoint="last")`` vs the in-memory policy (seed 0 of ``runner``)
    on two states."""
    ctrl, config = load_policy(run, checkpoint="last")
    rep = jax.tree.map(lambda x: x[0, 0], runner)  # device 0, seed 0
    env_params = build(config)[1]
    mem = policy_controller(rep.params, rep.stats.mean, rep.stats.var, config.env.gain_max,
                            hidden=tuple(config.ppo.hidden), init_sigma=config.ppo.init_sigma,
                            gain_filter=config.env.gain_filter, obs_segments=config.env.obs_segments,
                            sigma_nodes=env_params.filter_nodes)
    tp = env_params.traffic  # the run's nominal plant
    out = {"identical": [], "h": [], "stats_trained": bool(np.abs(rep.stats.mean).max() > 0
                                                           and not np.allclose(rep.stats.var, 1.0))}
    for amp in (0.004, 0.012):
        rho, v = paper_initial_condition(tp, amplitude=amp)
        plant = initial_state(tp, rho, v)
        obs = Observation(rho=plant.rho, v=plant.v, h_prev=plant.h_prev * 1.01, t=jnp.asarray(0.0), sent=plant.sent)
        key = jax.random.PRNGKey(0)
        h_loaded = np.asarray(ctrl.act(ctrl.init(obs, tp), obs, tp, key)[0])
        h_mem = np.asarray(mem.act(mem.init(obs, tp), obs, tp, key)[0])
        out["identical"].append(bool(np.array_equal(h_loaded, h_mem)))
        out["h"].append(h_loaded.tolist())
    try:
        load_policy(run, seed=3)
        out["bad_seed_rejected"] = False
    except ValueError:
        out["bad_seed_rejected"] = True
    return out


def xla_env(**extra) -> dict:
    """The environment of a training subprocess: CPU, the test XLA flags, ``flags`` added to XLA_FLAGS."""
    flags = with_test_flags(os.environ.get("XLA_FLAGS", ""), *extra.pop("flags", []))
    return {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu", **extra}


def start_two_devices() -> subprocess.Popen:
    """The two-device training (``TWO_DEVICES``), started in a subprocess; read by ``test_two_cpu_devices``."""
    argv = TINY[:]
    argv[argv.index("--num-envs") + 1] = "4"  # 2 environments per device
    return subprocess.Popen([sys.executable, "-c", TWO_DEVICES, json.dumps(argv)], cwd=REPO,
                            env=xla_env(flags=["--xla_force_host_platform_device_count=2"]),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def start_train_runs(root: Path) -> subprocess.Popen:
    """``train_runs(root)`` started in a subprocess (single CPU device, unoptimised XLA backend);
    its output goes to ``root/train_runs.log``."""
    code = "import sys; from pathlib import Path; sys.path[:0] = ['.', 'tests']; import tiny_runs; " \
           "tiny_runs.train_runs_or_mark(Path(sys.argv[1]))"
    log = open(root / "train_runs.log", "w")  # closed by wait_train_runs
    proc = subprocess.Popen([sys.executable, "-c", code, str(root)], cwd=REPO, env=xla_env(), stdout=log,
                            stderr=subprocess.STDOUT, text=True)
    proc.log = log
    return proc


def train_runs_or_mark(root: Path) -> None:
    """``train_runs``, leaving ``FAILED`` (the traceback) in ``root`` if it raises."""
    try:
        train_runs(root)
    except BaseException:
        import traceback

        (root / FAILED).write_text(traceback.format_exc())
        raise


def _log_tail(root: Path) -> str:
    return (root / "train_runs.log").read_text()[-4000:]


def _wait_for(root: Path, marker: str, timeout: float) -> None:
    """Wait for ``root / marker``, written by a training another test process runs (pytest-xdist workers
    share one session, ``conftest.py``), or by an earlier session; fail at once if that training failed."""
    t0 = time.monotonic()
    while not (root / marker).exists():
        assert not (root / FAILED).exists(), (root / FAILED).read_text()[-4000:]
        assert time.monotonic() - t0 < timeout, f"{root / marker} not written in time"
        time.sleep(0.5)


def wait_train_runs(proc: subprocess.Popen | None, root: Path, timeout: float = 900.0) -> None:
    """Wait until every run of ``train_runs`` is written; fail with the subprocess's output if it failed.
    ``proc`` None: the runs are written by another test process or were by an earlier session."""
    if proc is None:
        _wait_for(root, DONE, timeout)
        return
    proc.wait(timeout=timeout)
    proc.log.close()
    assert proc.returncode == 0, _log_tail(root)


def wait_run_a(proc: subprocess.Popen | None, root: Path, timeout: float = 900.0) -> Path:
    """Run A as soon as it is complete (``A.done``), while the other runs may still be training."""
    if proc is None:
        _wait_for(root, "A.done", timeout)
        return root / "A"
    t0 = time.monotonic()
    while not (root / "A.done").exists():
        assert proc.poll() is None or (root / "A.done").exists(), _log_tail(root)
        assert time.monotonic() - t0 < timeout, "run A not written in time"
        time.sleep(0.5)
    return root / "A"


TWO_DEVICES = r"""
import json, sys, tempfile
import jax, numpy as np
sys.path.insert(0, ".")
import train
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.learn.ppo import algorithm as ppo

orig, cache = ppo.make_train, {}
def shared(cfg, env_params, devices=None, *, env):  # resume reuses the compiled program
    key = (cfg, env_params, env)
    cache[key] = cache.get(key) or orig(cfg, env_params, devices, env=env)
    return cache[key]
ppo.make_train = shared

out = tempfile.mkdtemp()
argv = json.loads(sys.argv[1]) + ["--out-dir", out, "--keep-going"]
train.main(argv + ["--total-steps", "128"])
run = train.main(argv + ["--total-steps", "192", "--resume"])
r, meta = ckpt.load_checkpoint(run)
leaves = jax.tree_util.tree_leaves(r["params"]) + jax.tree_util.tree_leaves(r["opt_state"])
rows = open(f"{run}/learning_curve.csv").read().splitlines()
summary = json.load(open(f"{run}/summary.json"))
print("RESULT " + json.dumps({
    "device_count": jax.device_count(),
    "leading_axis": [int(np.shape(x)[0]) for x in leaves][:3],
    "params_replicated": all(np.array_equal(x[0], x[1]) for x in leaves),
    "stats_replicated": bool(np.array_equal(r["stats"]["mean"][0], r["stats"]["mean"][1])),
    "envs_differ": not np.array_equal(r["obs"][0], r["obs"][1]),
    "env_steps": meta["env_steps"], "n_rows": len(rows) - 1,
    "finite": bool(np.all(np.isfinite([float(x) for row in rows[1:] for x in row.split(",")]))),
    "final_reward": summary["final_eval"]["final_reward"],
}))
"""
