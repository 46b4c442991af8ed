"""Hardening: every bad input gets a clear error, no wrong result passes silently, no interruption
loses work. One test (or parametrised case) per case, on tiny grids.

The trainings run as subprocesses started together when the module's first training test asks for
them (``procs``): a reference run, a run stopped by SIGINT during its first compile, a run stopped by
SIGTERM after a chunk, and the fault-injection chain (SIGKILL at random points, then --resume), which
must end bit-identical to the reference with no temporary file left.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import leaves_equal
from report_helpers import previous_report
from tiny_runs import xla_env

import jaxtraffic as jt
from jaxtraffic import TrafficParams
from jaxtraffic.cli import evaluate as evaluate_cli
from jaxtraffic.cli import train as train_cli
from jaxtraffic.control import Controller, saturate
from jaxtraffic.io import files
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.config.checks import check_devices
from jaxtraffic.runs.policy import load_policy
from jaxtraffic.runs.session import StopSignals
from jaxtraffic.sim.outcome import Divergence

REPO = Path(__file__).resolve().parents[1]
# one member (the default is a population of 2): these runs are counted per member below;
# the population itself: test_train.test_population_run
TINY = ["--num-seeds", "1", "--n-points", "21", "--delay", "0.5", "--max-delay-steps", "20", "--num-envs", "4",
        "--num-steps", "8",
        "--updates-per-chunk", "2", "--update-epochs", "2", "--num-minibatches", "2", "--horizon-s", "3",
        "--eval-horizon-s", "2", "--keep-going", "--quiet", "--obs-segments", "0", "--val-horizon-s", "2"]
CHUNK = 4 * 8 * 2
N_CHUNKS = 8
P21 = TrafficParams(n_points=21, delay=4.0)


# ----------------------------------------------------------------------------- the nominal model and the plant
@pytest.mark.parametrize("nominal, match", [
    (TrafficParams(delay=4.0), "nominal.n_points=201 differs"),
    (TrafficParams(n_points=21, delay=4.0, dt=0.05), "nominal.dt=0.05 differs"),
    (TrafficParams(n_points=21, delay=4.0, L=900.0), "nominal.L=900.0 differs"),
])
def test_nominal_on_another_grid_is_rejected(nominal, match):
    with pytest.raises(ValueError, match=match):
        jt.simulate(P21, jt.backstepping(4.0), n_steps=10, nominal=nominal)
    with pytest.raises(ValueError, match=match):
        jt.simulate_batch(jt.stack_params(delay=[0.0, 4.0], n_points=21), jt.backstepping(4.0), n_steps=10,
                          nominal=nominal)


def test_nominal_with_other_physics_is_accepted():
    res = jt.simulate(P21, jt.lyapunov(1.0), n_steps=10, nominal=P21.replace(alpha=0.3))
    assert np.isfinite(float(res.metrics["final_reward"]))


# ----------------------------------------------------------------------------- PPO hyperparameters
@pytest.mark.parametrize("argv, match", [
    (["--lr", "-1"], "lr = -1.0: must be > 0"),
    (["--gamma", "5"], "gamma = 5.0: must lie in (0.0, 1.0]"),
    (["--clip-eps", "-1"], "clip_eps = -1.0: must be > 0"),
    (["--num-envs", "0"], "num_envs = 0: must be >= 1"),
    (["--num-seeds", "0"], "num_seeds = 0: must be >= 1"),
    (["--num-steps", "-5"], "num_steps = -5: must be >= 1"),
    (["--num-minibatches", "0"], "num_minibatches = 0: must be >= 1"),
    (["--num-minibatches", "3"], "must divide the batch"),
    (["--updates-per-chunk", "0"], "updates_per_chunk = 0: must be >= 1"),
    (["--stop-patience", "0"], "stop_patience = 0: must be >= 1"),
    (["--total-steps", "-1"], "total_steps = -1: must be >= 1"),
    (["--lr", "nan"], "lr = nan: must be finite"),
    (["--gain-filter", "5"], "gain_filter = 5.0"),
    (["--max-wall-s", "0"], "max_wall_s = 0.0"),
    (["--eval-horizon-s", "0.01"], "must be >= one time step"),
])
def test_bad_training_flags_exit_2_before_anything_is_written(argv, match, tmp_path, capsys):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        train_cli.main(TINY + argv + ["--out-dir", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
    assert not out.exists()


def test_config_accepts_numpy_scalars_and_normalises_them():
    cfg = TrainConfig.make(plant={"n_points": np.int64(21)}, ppo={"lr": np.float32(0.5)},
                           run={"max_wall_s": float("inf")})
    assert type(cfg.plant.n_points) is int and type(cfg.ppo.lr) is float
    with pytest.raises(ValueError, match="must be an integer"):
        TrainConfig.make(ppo={"num_envs": 4.0})


def test_device_count_constraints():
    cfg = TrainConfig.make(ppo={"num_envs": 4, "num_steps": 8, "num_minibatches": 2})
    check_devices(cfg, 2)
    with pytest.raises(ValueError, match=r"num_envs = 4: must be divisible by the number of devices"):
        check_devices(cfg, 3)
    with pytest.raises(ValueError, match="batch of each device"):
        check_devices(TrainConfig.make(ppo={"num_envs": 4, "num_steps": 1, "num_minibatches": 4}), 2)


# ----------------------------------------------------------------------------- non-finite values
def test_saturate_maps_nan_to_a_defined_value():
    p = TrafficParams()
    h = saturate(jnp.array([jnp.nan, jnp.inf, -jnp.inf, 1.0]), p)
    np.testing.assert_array_equal(np.asarray(h), [p.h_bar, p.h_max, p.h_min, 1.0])


def _nan_act(settings, cstate, obs, nominal, key):
    return jnp.where(obs.t >= settings, jnp.nan, nominal.h_bar) * jnp.ones_like(obs.rho), cstate


def test_nan_controller_output_marks_the_environment_diverged():
    ctrl = Controller(settings=jnp.asarray(1.0), act_fn=_nan_act)  # NaN from t = 1 s
    m = jt.simulate(P21, ctrl, n_steps=30).metrics
    assert bool(m["diverged"]) and int(m["diverged_reason"]) == Divergence.CONTROL
    assert float(m["diverged_at_s"]) == pytest.approx(1.0)
    assert np.isfinite(float(m["control_effort"]))  # only the accepted steps count
    # a traced NaN gain (not rejected at construction) gives the same flag
    m = jax.jit(lambda k: jt.simulate(P21, jt.lyapunov(k), n_steps=5).metrics)(jnp.nan)
    assert bool(m["diverged"]) and int(m["diverged_reason"]) == Divergence.CONTROL
    healthy = jt.simulate(P21, jt.lyapunov(1.0), n_steps=5).metrics
    assert int(healthy["diverged_reason"]) == Divergence.NONE


def test_traced_non_finite_initial_condition_is_flagged():
    rho, v = jt.paper_initial_condition(P21)
    m = jax.jit(lambda r: jt.simulate(P21, jt.lyapunov(1.0), n_steps=5, rho0=r, v0=v).metrics)(rho.at[3].set(jnp.nan))
    assert bool(m["diverged"]) and int(m["diverged_reason"]) == Divergence.INITIAL
    assert float(m["diverged_at_s"]) == 0.0
    with pytest.raises(ValueError, match="physical region"):  # a concrete one is an error
        jt.simulate(P21, n_steps=5, rho0=rho.at[3].set(jnp.nan), v0=v)


@pytest.mark.parametrize("field, value", [("delay", 12.0), ("delay", -0.1), ("alpha", -0.5), ("alpha", 1.5),
                                          ("dt", -0.1), ("alpha_noise", -1.0), ("tau_acc", jnp.nan)])
def test_traced_parameters_out_of_range_are_flagged_not_run(field, value):
    """A traced plant parameter outside its range (a delay beyond the 10 s buffer, a negative one, alpha
    outside [0, 1], ...) freezes the plant at step 0 with its own reason instead of running another system."""
    p = TrafficParams(n_points=21, max_delay_steps=100)
    m = jax.jit(lambda x: jt.simulate(p.replace(**{field: x}), jt.lyapunov(1.0), n_steps=5).metrics)(
        jnp.float32(value))
    assert bool(m["diverged"]) and int(m["diverged_reason"]) == Divergence.PARAMS and float(m["diverged_at_s"]) == 0
    ok = jax.jit(lambda x: jt.simulate(p.replace(delay=x), jt.lyapunov(1.0), n_steps=5).metrics)(jnp.float32(10.0))
    assert int(ok["diverged_reason"]) == Divergence.NONE  # the buffer's full 10 s is allowed


def test_given_alphas_outside_zero_one_are_an_error():
    with pytest.raises(ValueError, match=r"alphas must lie in \[0, 1\] \(ACC shares\), got values in \[-1, -1\]"):
        jt.simulate(P21, n_steps=5, alpha_input=jt.AlphaInput(alphas=-np.ones(5)))


@pytest.mark.parametrize("delay", [jnp.nan, -4.0])
def test_traced_invalid_backstepping_delay_is_flagged_not_lyapunov(delay):
    m = jax.jit(lambda d: jt.simulate(P21, jt.backstepping(d), n_steps=5).metrics)(jnp.float32(delay))
    assert bool(m["diverged"]) and int(m["diverged_reason"]) == Divergence.CONTROL
    good = jax.jit(lambda d: jt.simulate(P21, jt.backstepping(d), n_steps=5).metrics)(jnp.float32(0.0))
    assert int(good["diverged_reason"]) == Divergence.NONE


def test_nan_action_terminates_the_training_environment():
    from jaxtraffic.learn import env as learn_env
    ep = learn_env.make_env_params(TrafficParams(n_points=21, delay=0.5, max_delay_steps=20), horizon=30)
    _, state = learn_env.reset_env(jax.random.PRNGKey(0), ep)
    _, _, r, done, info = jax.jit(learn_env.step_env)(jax.random.PRNGKey(1), state, jnp.full((3,), jnp.nan), ep)
    assert bool(info["terminated"]) and bool(done) and float(r) == -ep.diverge_penalty


def test_json_distinguishes_nan_from_never(tmp_path):
    obj = {"final_reward": np.float32(np.nan), "time_to_reward_target_s": np.inf, "low": -np.inf,
           "arr": np.array([1.0, np.nan]), "diverged_at_s": None}
    js = files.to_jsonable(obj)
    assert js == {"final_reward": "nan", "time_to_reward_target_s": None, "low": "-inf", "arr": [1.0, "nan"],
                  "diverged_at_s": None}
    files.write_json(tmp_path / "x.json", obj)  # strict JSON (no NaN literal)
    back = files.from_jsonable(json.loads((tmp_path / "x.json").read_text()))
    assert np.isnan(back["final_reward"]) and back["time_to_reward_target_s"] is None and back["low"] == -np.inf


def test_json_writes_float32_at_its_shortest_round_trip_decimal(tmp_path):
    """A float32 value is written as the shortest decimal that reads back as the same float32 (the edges
    included: subnormal, the largest, -0, non-finite), in fewer characters than its float64 repr; float64,
    integers and booleans are written as before."""
    rng = np.random.default_rng(0)
    a = (rng.standard_normal(4000) * 10.0 ** rng.integers(-12, 12, 4000)).astype(np.float32)
    a[:6] = [np.finfo(np.float32).smallest_subnormal, np.finfo(np.float32).max, -0.0, np.inf, -np.inf, np.nan]
    obj = {"f32": a.reshape(40, 100), "scalar": np.float32(0.1), "f64": np.float64(0.1) / 3, "i": np.arange(3),
           "b": np.array([True, False])}
    files.write_json(tmp_path / "x.json", obj)
    back = files.from_jsonable(json.loads((tmp_path / "x.json").read_text()))
    got = np.asarray([np.inf if v is None else v for v in np.ravel(np.asarray(back["f32"], object))], np.float32)
    np.testing.assert_array_equal(got, a)  # every value, bit for bit (NaN as NaN)
    assert np.signbit(got[2]) and back["scalar"] == 0.1 and back["f64"] == 0.1 / 3
    assert back["i"] == [0, 1, 2] and back["b"] == [True, False]
    finite = a[np.isfinite(a)]
    assert sum(len(repr(float(str(x)))) for x in finite) < 0.7 * sum(len(repr(float(x))) for x in finite)
    assert files.as_lists(np.float32(2.5)) == 2.5 and files.as_lists(np.zeros((2, 0), np.float32)) == [[], []]


def test_json_lists_of_scalars_on_one_line(tmp_path):
    """``write_json`` puts a list of numbers, booleans and nulls on one line (the recorded series: a third of the
    bytes), keeps nested lists, dicts and strings (a string that looks like a list included) as they are, and reads
    back equal."""
    obj = {"series": np.array([1.5, -2e-07, 3.0]), "flags": [True, False, None], "nested": [[1, 2], [3]],
           "text": "[1,\n 2]", "mixed": [1, "nan"], "empty": [], "rows": [{"x": [0.25, 4]}]}
    files.write_json(tmp_path / "x.json", obj)
    text = (tmp_path / "x.json").read_text()
    for line in ('"series": [1.5, -2e-07, 3.0]', '"flags": [true, false, null]', '  [1, 2],', '"x": [0.25, 4]',
                 '"text": "[1,\\n 2]"', '"empty": []'):
        assert line in text, line
    assert '"mixed": [\n' in text and text.endswith("}\n")
    assert json.loads(text) == files.to_jsonable(obj)


def test_report_reads_nan_strings(tmp_path):
    from jaxtraffic.paper.report import write_report
    entry = {k: "nan" for k in ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward",
                                "control_effort")}
    entry.update({"diverged": True, "time_to_reward_-0.1_s": None, "t_settle_rho_s": None, "t_settle_v_s": None})
    meta = {"policy": {"run_dir": "r"}, "policy_delay0": {"description": "d"}, "seeds": [0],
            "grid": {"n_points": 21, "dx_m": 50.0, "dt_s": 0.1, "horizon_s": 1.0, "record_every": 1}}
    write_report(tmp_path / "R.md", [], {"delay4": {"ppo": entry}}, meta, [], [])
    assert "| nan |" in (tmp_path / "R.md").read_text()


# ----------------------------------------------------------------------------- more input checks
@pytest.mark.parametrize("kwargs, match", [
    ({"delay": float("inf")}, "delay must be finite"),
    ({"alpha_noise": float("inf")}, "alpha_noise must be finite"),
    ({"L": float("inf")}, "L must be finite"),
    ({"L": "1000"}, "L must be a number, got '1000'"),
    ({"dt": float("nan")}, "dt must be finite"),
])
def test_traffic_params_reject_non_finite_and_strings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrafficParams(**kwargs)


def test_traffic_params_accept_numpy_integers():
    p = TrafficParams(n_points=np.int64(21), max_delay_steps=np.int32(50))
    assert type(p.n_points) is int and p.n_points == 21 and type(p.max_delay_steps) is int


@pytest.mark.parametrize("kwargs, match", [
    ({"n_steps": 10.0}, r"n_steps must be an int in \[1, 2\*\*31\) \(the rollout counts steps in int32\), got 10.0"),
    ({"n_steps": 0}, "n_steps must be an int in"),
    ({"n_steps": 10, "record_every": -1}, "record_every must be an int >= 0"),
    ({"n_steps": 10, "record_every": 3}, "not a multiple of record_every"),
])
def test_simulate_step_arguments(kwargs, match):
    kwargs = dict(kwargs)
    with pytest.raises(ValueError, match=match):
        if "record_every" in kwargs:  # Record checks its own field on construction
            kwargs["record"] = jt.Record(every=kwargs.pop("record_every"))
        jt.simulate(P21, **kwargs)


@pytest.mark.parametrize("make, match", [
    (lambda: jt.backstepping(float("nan")), "assumed delay must be finite"),
    (lambda: jt.backstepping(4.0, k=float("inf")), "backstepping gain k must be finite"),
    (lambda: jt.backstepping(-1.0), "assumed delay must be >= 0"),
    (lambda: jt.lyapunov(float("nan")), "lyapunov gain k must be finite"),
])
def test_controller_settings_validated(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_controllers_can_be_built_inside_jit():
    @jax.jit
    def run(d):
        return jt.backstepping(4.0).settings.delay + jt.lyapunov(1.0).settings.k + jt.backstepping(d).settings.delay

    assert float(run(1.0)) == 6.0


# ----------------------------------------------------------------------------- file permissions
def test_written_files_honour_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        files.atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o640
    files.atomic_write_text(tmp_path / "b.txt", "x")
    assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o666 & ~old


# ----------------------------------------------------------------------------- signals (unit)
def test_stop_signals_set_a_flag_and_restore_the_handlers():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with StopSignals(print) as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        assert stop.signum == signal.SIGTERM  # no exception: only the flag
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before


# ----------------------------------------------------------------------------- output directories
def test_out_dir_that_is_a_file_or_under_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    for out, match in ((f, "exists and is not a directory"), (f / "sub", "is a file, not a directory")):
        with pytest.raises(SystemExit) as exc:
            train_cli.main(TINY + ["--out-dir", str(out)])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert match in err and "Traceback" not in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_out_dir_not_writable(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    with pytest.raises(SystemExit) as exc:
        train_cli.main(TINY + ["--out-dir", str(ro / "run")])
    assert exc.value.code == 2 and "not writable" in capsys.readouterr().err


@pytest.mark.parametrize("argv, match", [
    (["--horizon", "-5"], "--horizon must be a number of seconds in (0, 1e+07], got -5.0"),
    (["--horizon", "inf"], "--horizon must be a number of seconds in (0, 1e+07], got inf"),
    (["--horizon", "1e30"], "--horizon must be a number of seconds in (0, 1e+07], got 1e+30"),
    (["--robust-horizon", "0"], "--robust-horizon must be"),
    (["--noise-seeds", "0"], "--noise-seeds must lie in [1, 1000], got 0"),
    (["--noise-seeds", "1000001"], "--noise-seeds must lie in [1, 1000], got 1000001"),
    (["--seeds", "8"], "--seeds was renamed --noise-seeds"),
    (["--seed", "8"], "Unrecognized options: --seed"),
    (["--robust-grid", "3"], "--robust-grid must look like AxB"),
    (["--robust-grid", "1000000x1000000"], "--robust-grid 1000000x1000000 has 1000000000000 cells; at most 10000"),
    (["--plants", "paper,moon"], "--plants must name one or both of"),
    (["--reference-grid", "801"], "--reference-grid must look like AxB"),
    (["--reference-grid", "2x1"], "--reference-grid needs >= 3 points"),
    (["--n-points", "2"], "--n-points must be >= 3"),
    (["--fair", "-1"], "--fair must be >= 0 test scenarios"),
    (["--fair-other", "-2"], "--fair-other must be >= 0 test scenarios"),
    (["--split-runs", "no/such/folder"], "--split-runs no/such/folder: not a folder"),
])
def test_bad_evaluation_flags(argv, match, tmp_path, capsys):
    out = tmp_path / "results"
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(argv + ["--out", str(out)])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
    assert not out.exists()


def test_evaluate_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(["--out", str(f), "--horizon", "1"])
    assert exc.value.code == 2 and "exists and is not a directory" in capsys.readouterr().err


def test_resume_refuses_a_directory_without_checkpoint(tmp_path, capsys):
    empty = tmp_path / "empty"
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(empty), "--resume"])
    assert exc.value.code == 2 and "nothing to resume" in capsys.readouterr().err
    assert not empty.exists()
    cfg_only = tmp_path / "cfg_only"
    cfg_only.mkdir()
    (cfg_only / "config.json").write_text(json.dumps(files.to_jsonable({"version": 2, "config": {}})))
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(cfg_only), "--resume"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "no checkpoint" in err and "first chunk" in err


# ----------------------------------------------------------------------------- the trainings
def _env() -> dict:
    return xla_env(PYTHONPATH=str(REPO))


def _start(out: Path, *extra: str, env: dict | None = None, quiet: bool = True) -> subprocess.Popen:
    flags = TINY if quiet else [x for x in TINY if x != "--quiet"]
    return subprocess.Popen([sys.executable, str(REPO / "train.py"), *flags, "--out-dir", str(out), *extra],
                            cwd=REPO, env=env or _env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _resume(out: Path, total: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(REPO / "train.py"), "--out-dir", str(out), "--resume",
                             "--total-steps", str(total), "--keep-going", "--quiet"],
                            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 400.0) -> bool:
    t0 = time.time()
    while not path.exists():
        if proc.poll() is not None or time.time() - t0 > timeout:
            return False
        time.sleep(0.05)
    return True


def _wait_for_new(path: Path, proc: subprocess.Popen, timeout: float = 400.0) -> bool:
    """Wait until ``proc`` has (re)written ``path``."""
    before = path.stat().st_mtime_ns if path.exists() else None
    t0 = time.time()
    while not path.exists() or path.stat().st_mtime_ns == before:
        if proc.poll() is not None or time.time() - t0 > timeout:
            return False
        time.sleep(0.02)
    return True


@pytest.fixture(scope="module")
def procs(tmp_path_factory):
    """Start the reference run, the SIGINT-at-compile run and the SIGTERM-after-a-chunk run together."""
    root = tmp_path_factory.mktemp("hardening")
    total = str(N_CHUNKS * CHUNK)
    out = {"root": root,
           "ref": _start(root / "ref", "--total-steps", total),
           "early": _start(root / "early", "--total-steps", total, quiet=False),
           "term": _start(root / "term", "--total-steps", str(1000 * CHUNK))}
    early = out["early"]
    out["early_stdout"] = []
    for line in early.stdout:  # the handlers are installed once it says it compiles
        out["early_stdout"].append(line)
        if line.startswith("compiling"):
            early.send_signal(signal.SIGINT)
            break
    yield out
    for p in out.values():
        if isinstance(p, subprocess.Popen) and p.poll() is None:
            p.kill()
            p.communicate()


def _finish(proc: subprocess.Popen, timeout: float = 500.0) -> tuple[int, str, str]:
    stdout, stderr = proc.communicate(timeout=timeout)
    return proc.returncode, stdout, stderr


@pytest.fixture(scope="module")
def ref_run(procs):
    rc, _, err = _finish(procs["ref"])
    assert rc == 0, err[-3000:]
    return procs["root"] / "ref"


@pytest.mark.slow
def test_sigint_during_the_first_compile(procs):
    rc, stdout, err = _finish(procs["early"])
    assert rc == 130, (rc, err[-2000:])  # not 139 (segfault), not 0
    assert "SIGINT received" in err and "no checkpoint exists yet" in err
    assert "steps]" not in stdout  # no chunk ran after the signal
    assert not (procs["root"] / "early" / ckpt.CHECKPOINT).exists()


@pytest.mark.slow
def test_sigterm_saves_a_checkpoint_and_exits_143(procs):
    term = procs["root"] / "term"
    assert _wait_for(term / ckpt.CHECKPOINT, procs["term"]), procs["term"].communicate()[1][-2000:]
    procs["term"].send_signal(signal.SIGTERM)
    rc, _, err = _finish(procs["term"])
    assert rc == 143, (rc, err[-2000:])
    assert "SIGTERM" in err and "continue with resume" in err
    _, meta = ckpt.load_checkpoint(term)
    summary = json.loads((term / ckpt.SUMMARY).read_text())
    assert summary["interrupted"] is True and summary["env_steps"] == meta["env_steps"] >= CHUNK
    assert not list(term.glob(".*.tmp"))




def _rows(run: Path) -> list[list[str]]:
    lines = (run / "learning_curve.csv").read_text().splitlines()
    head = lines[0].split(",")
    wall = head.index("wall_s")
    return [[x for i, x in enumerate(line.split(",")) if i != wall] for line in lines]


@pytest.mark.slow
def test_sigkill_at_random_points_then_resume_is_bit_identical(procs, ref_run):
    rng = random.Random(int(os.environ.get("HARDENING_SEED", time.time_ns() % 10_000)))
    run = procs["root"] / "killed"
    total = N_CHUNKS * CHUNK
    kills = []
    proc = _start(run, "--total-steps", str(total))
    for _ in range(2):  # SIGKILL twice, at a random moment after this process has written a checkpoint
        if not _wait_for_new(run / ckpt.CHECKPOINT, proc):
            break
        time.sleep(rng.uniform(0.0, 0.5))
        if proc.poll() is None:
            proc.kill()
            kills.append(ckpt.load_checkpoint(run)[1]["env_steps"])
        proc.communicate()
        proc = _resume(run, total)
    assert kills, "the training ended before it could be killed"
    # a write interrupted by SIGKILL leaves a temporary file behind: the next start removes it
    (run / ".checkpoint.msgpack.stale_12.tmp").write_bytes(b"x" * 100)
    rc, _, err = _finish(proc)
    if rc == 0 and (run / ".checkpoint.msgpack.stale_12.tmp").exists():  # the last resume had already started
        rc, _, err = _finish(_resume(run, total))
    assert rc == 0, err[-3000:]
    state_ref, meta_ref = ckpt.load_checkpoint(ref_run)
    state, meta = ckpt.load_checkpoint(run)
    assert meta["env_steps"] == meta_ref["env_steps"] == total
    assert leaves_equal(state, state_ref), kills  # params, Adam state, environments, statistics, keys
    assert _rows(run) == _rows(ref_run)
    s_ref, s = (json.loads((r / ckpt.SUMMARY).read_text()) for r in (ref_run, run))
    assert s["final_eval"] == s_ref["final_eval"]
    assert not list(run.glob(".*.tmp"))


@pytest.mark.slow
def test_run_directory_files_are_0644(ref_run):
    for name in (ckpt.CONFIG, ckpt.CHECKPOINT, ckpt.SUMMARY, "learning_curve.csv"):
        assert stat.S_IMODE((ref_run / name).stat().st_mode) == 0o644, name  # the test process umask is 022


# ----------------------------------------------------------------------------- broken run directories
def _copy(ref_run: Path, tmp_path: Path) -> Path:
    d = tmp_path / "copy"
    shutil.copytree(ref_run, d)
    return d


def _config(run: Path) -> dict:
    return json.loads((run / ckpt.CONFIG).read_text())


def _damage_ckpt(kind: str):
    def damage(run: Path) -> None:  # both the last state (resume) and the best checkpoint (load_policy)
        for name in (ckpt.CHECKPOINT, ckpt.BEST):
            _damage_file(run / name, kind)
    return damage


def _damage_file(p: Path, kind: str) -> None:
    data = bytearray(p.read_bytes())
    if kind == "truncated":
        p.write_bytes(bytes(data[: len(data) // 2]))
    elif kind == "empty":
        p.write_bytes(b"")
    else:  # 50 flipped bytes in the middle
        rng = np.random.default_rng(0)
        for i in rng.choice(np.arange(100, len(data) - 100), 50, replace=False):
            data[i] ^= 0xFF
        p.write_bytes(bytes(data))


def _edit_config(edit):
    def damage(run: Path) -> None:
        cfg = _config(run)
        edit(cfg)
        (run / ckpt.CONFIG).write_text(json.dumps(cfg))
    return damage


def _set(section: str, key: str, value):
    return _edit_config(lambda c: c["config"][section].__setitem__(key, value))


def _set_both(section: str, key: str, old: str, new: str, value):
    """The field changed in config.json and in config.toml alike (the run's truth): a consistent config that no
    longer matches the checkpoint."""
    def damage(run: Path) -> None:
        _set(section, key, value)(run)
        toml = run / "config.toml"
        text = toml.read_text()
        assert f"{key} = {old}\n" in text
        toml.write_text(text.replace(f"{key} = {old}\n", f"{key} = {new}\n"))
    return damage


BROKEN = {
    "truncated": (_damage_ckpt("truncated"), ".msgpack: truncated or not msgpack"),
    "empty": (_damage_ckpt("empty"), ".msgpack: empty file"),
    "flipped": (_damage_ckpt("flipped"), ".msgpack: checksum mismatch"),
    # config.json without its env section reads as the defaults, which config.toml (the truth) contradicts
    "no_env": (_edit_config(lambda c: c["config"].pop("env")), "[env] horizon_s = 3.0, but the run's config.json"),
    "foreign": (lambda run: (run / ckpt.CONFIG).write_text('{"name": "something else"}'),
                "config.json: not a config tree written by train.py"),
    "not_json": (lambda run: (run / ckpt.CONFIG).write_text('{"config": '), "config.json: unreadable or not valid"),
    "wrong_type": (_set("plant", "n_points", "21"), "config.json: n_points = '21': must be an integer"),
    "grid": (_set_both("plant", "n_points", "21", "41", 41), "do not belong together"),  # passes the config checks
    "gain_filter": (_set("env", "gain_filter", 5), "config.json: gain_filter = 5.0"),
    "gain_max_nan": (_set("env", "gain_max", float("nan")), "config.json: gain_max = nan: must be finite"),
    # config.json edited after training (config.toml, the truth, says otherwise), or made pathological
    "edited": (_set("env", "gain_max", 0.123), "says 0.123; only the run control may be edited"),
    "algo": (_set_both("run", "algo", '"ppo"', '"gradient"', "gradient"), "do not belong together"),
    "nested": (lambda run: (run / ckpt.CONFIG).write_text("[" * 100_000 + "]" * 100_000),
               "config.json: unreadable or not valid JSON (RecursionError"),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_run_directory_gives_one_line_errors(case, ref_run, tmp_path, capsys):
    run = _copy(ref_run, tmp_path)
    damage, match = BROKEN[case]
    damage(run)
    with pytest.raises(ValueError, match="^.*" + __import__("re").escape(match)):
        load_policy(run)
    with pytest.raises(SystemExit) as exc:  # evaluate.py --run: one line, no traceback
        evaluate_cli.main(["--run", str(run), "--out", str(tmp_path / "res"), "--horizon", "1"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and match in err and "Traceback" not in err and err.count("\n") == 1, err
    assert not (tmp_path / "res").exists()
    if case != "grid":  # (a grid mismatch is found when the checkpoint is restored, after compiling)
        with pytest.raises(SystemExit) as exc:
            train_cli.main(["--out-dir", str(run), "--resume", "--quiet"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and match in err and "Traceback" not in err, err


@pytest.mark.slow
def test_restore_rejects_mismatching_shapes(ref_run):
    state, _ = ckpt.load_checkpoint(ref_run)
    template = jax.tree.map(lambda x: np.zeros_like(x), state)
    template["obs"] = np.zeros(np.shape(state["obs"])[:-1] + (5,))
    with pytest.raises(ValueError, match="do not belong together"):
        ckpt.restore_runner(template, state, "x/checkpoint.msgpack")


@pytest.mark.slow
def test_resume_with_another_device_count_explains(ref_run, tmp_path):
    run = _copy(ref_run, tmp_path)
    env = _env()
    env["XLA_FLAGS"] += " --xla_force_host_platform_device_count=2"
    proc = subprocess.run([sys.executable, str(REPO / "train.py"), "--out-dir", str(run), "--resume", "--quiet"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "written by a run with 1 device(s), this one has 2" in proc.stderr
    assert "xla_force_host_platform_device_count=1" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_resume_keeps_the_saved_run_control_and_refuses_other_changes(ref_run):
    saved = load_config(ref_run)
    cfg = saved.updated(ppo={"lr": 0.5, "num_seeds": 3},
                        run={"total_steps": 7 * CHUNK, "out_dir": str(ref_run), "resume": True})
    with pytest.raises(ValueError, match=r"would change it: --lr 0.5 \(the run's value: 0.001\), --num-seeds 3"):
        train_cli.resumed_config(cfg, {"lr": 0.5, "num_seeds": 3, "total_steps": 7 * CHUNK, "n_points": 21})
    # an equal value is no change; a run-control flag applies; one not given keeps the run's saved value
    default = TrainConfig().updated(run={"out_dir": str(ref_run), "resume": True, "total_steps": 7 * CHUNK},
                                    plant={"n_points": 21})
    merged = train_cli.resumed_config(default, {"total_steps": 7 * CHUNK, "n_points": 21, "resume": True})
    assert merged.run.total_steps == 7 * CHUNK and merged.run.resume and merged.run.out_dir == str(ref_run)
    assert merged.run.keep_going == saved.run.keep_going and merged.run.max_wall_s == saved.run.max_wall_s
    assert merged.updated(run={"total_steps": saved.run.total_steps, "resume": False}) == saved.updated(
        run={"out_dir": str(ref_run)})


def test_crafted_checkpoint_without_checksum_wrapper_is_rejected(tmp_path):
    import msgpack
    (tmp_path / ckpt.CHECKPOINT).write_bytes(msgpack.packb({"format": ckpt.FORMAT, "version": 1, "payload": 3}))
    with pytest.raises(ValueError, match="malformed checkpoint"):
        ckpt.load_checkpoint(tmp_path)
    (tmp_path / ckpt.CHECKPOINT).write_bytes(msgpack.packb([1, 2, 3]))
    with pytest.raises(ValueError, match="not a jaxtraffic checkpoint"):
        ckpt.load_checkpoint(tmp_path)


# ----------------------------------------------------------------------------- signals and pipes
@pytest.mark.slow
def test_evaluate_interrupted_exits_cleanly_and_leaves_its_output_as_it_was(ref_run, tmp_path):
    """SIGINT while evaluate.py computes (its figure and numerics threads running): 130, one line, no abort, no
    swallowed interrupt, and --out still holds the earlier report and nothing else (SIGTERM and SIGHUP take the
    same path, ``cli.staging.signals_raise``)."""
    sig = signal.SIGINT
    out = previous_report(tmp_path / "res")  # a previous report of evaluate.py's
    proc = subprocess.Popen([sys.executable, str(REPO / "evaluate.py"), "--run", str(ref_run), "--out", str(out),
                             "--horizon", "4", "--noise-seeds", "1", "--robust-grid", "2x2", "--gradient", "none",
                             "--plants", "paper"],
                            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:  # the robustness map runs beside the figure and numerics threads
        if "robustness map" in line:
            proc.send_signal(sig)
            break
    rc, _, err = _finish(proc, timeout=300)
    assert rc == 128 + sig, (rc, err[-2000:])
    assert f"interrupted ({signal.Signals(sig).name}): nothing was written to {out}" in err
    assert "Traceback" not in err and "terminate called" not in err, err[-2000:]
    assert sorted(p.name for p in out.iterdir()) == [".jaxtraffic-report", "REPORT.md"]  # and the marker unchanged
    assert (out / "REPORT.md").read_text() == "earlier" and not list(tmp_path.glob(".res.jaxtraffic-partial-*"))


@pytest.mark.slow
def test_closed_stdout_and_ctrl_c_at_import_give_no_traceback(tmp_path):
    grad = ["gradient", "--policy", "gains", "--n-points", "21", "--train-delays", "1",
            "--train-horizon-s", "2", "--steps-per-chunk", "1", "--eval-horizon-s", "2", "--grad-steps", "3"]
    proc = subprocess.Popen([sys.executable, str(REPO / "train.py"), *grad, "--out-dir", str(tmp_path / "g")],
                            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.readline()  # like `train.py ... | head -1`: the printing stops, the training goes on to its end
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=300) == 0 and "standard output was closed (broken pipe)" in err, err[-2000:]
    assert "Traceback" not in err and err.count("broken pipe") == 1
    summary = json.loads((tmp_path / "g" / ckpt.SUMMARY).read_text())
    assert summary["interrupted"] is False
    early = subprocess.Popen([sys.executable, str(REPO / "train.py"), "--help"], cwd=REPO, env=_env(),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(0.3)  # still importing jax
    early.send_signal(signal.SIGINT)
    rc, _, err = _finish(early, timeout=60)
    assert rc == 130 and "Traceback" not in err, (rc, err)


@pytest.mark.slow
def test_ctrl_c_under_a_closed_pipe_saves_summarises_and_exits_130(tmp_path):
    """``train.py ... | tee log``, then Ctrl-C: the reader dies first, the next progress line meets a closed pipe;
    the printing stops, the run does not: the last completed chunk (the second or later) is checkpointed, not
    the session's first one (saved otherwise: every 10th), summary.json is written, exit 130 (not 2)."""
    run = tmp_path / "piped"
    proc = _start(run, "--total-steps", str(1000 * CHUNK), quiet=False)
    lines = []
    for line in proc.stdout:  # two chunks' progress lines, then the reader goes and Ctrl-C arrives
        lines.append(line)
        if sum(x.startswith("[") and "steps]" in x for x in lines) == 2 or len(lines) > 50:
            break
    proc.stdout.close()
    proc.send_signal(signal.SIGINT)
    err = proc.stderr.read()
    rc = proc.wait(timeout=300)
    assert rc == 130, (rc, "".join(lines), err[-3000:])
    assert "SIGINT received" in err and "standard output was closed (broken pipe)" in err
    assert "Traceback" not in err and "continue with resume" in err, err[-2000:]
    _, meta = ckpt.load_checkpoint(run)
    summary = json.loads((run / ckpt.SUMMARY).read_text())
    assert summary["interrupted"] is True and summary["env_steps"] == meta["env_steps"] >= 2 * CHUNK


@pytest.mark.slow
def test_robust_horizon_below_one_step_is_a_flag_error(ref_run, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        evaluate_cli.main(["--run", str(ref_run), "--out", str(tmp_path / "res"), "--robust-horizon", "1e-300"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--robust-horizon must be at least one time step (0.1 s)" in err, err
    assert not (tmp_path / "res").exists()
