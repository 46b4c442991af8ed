"""Shared fixtures and helpers for the core test suite (tiny grids, a few hundred steps).

Precision: the library runs in float32 by default. Tests that need float64 (oracle digits, exact
mass balance, convergence order) use the ``x64`` fixture, which enables x64 only for the duration
of that test (``jax.enable_x64`` context manager), never globally.

Training: the suite trains once. ``tiny_runs_root`` (session scope) holds the run directories of the
one tiny training session (``tiny_runs.py``) that ``test_train.py`` reads; ``test_evaluate.py``
evaluates its run A (``tiny_run_a``). The session starts in the background right after collection.

Workers (pytest-xdist, ``-n 2``): the controlling process gives every worker one directory for the
training session and one compilation cache (``pytest_configure``); worker gw0 trains, the others wait for
its files (``tiny_runs.wait_*``), and gw0 waits for the training to end before it leaves.
"""

from __future__ import annotations

import gc
import os
import shutil
import signal
import subprocess
import tempfile
from pathlib import Path

import xla_flags

# The suite runs on ONE XLA device (as a user's program would with JAXTRAFFIC_NO_DEVICE_SPLIT=1),
# so that its figures do not depend on the machine's core count; the multi-device paths are tested
# in subprocesses that set their device count explicitly (tests/test_sharding.py, test_train.py).
os.environ.setdefault("JAXTRAFFIC_NO_DEVICE_SPLIT", "1")
# cheaper compilation in the test process and its subprocesses (tests/xla_flags.py)
xla_flags.apply()
# The command-line jobs' persistent compilation cache (jaxtraffic.platform.compile_cache) goes to a directory of
# this session, never the user's ~/.cache; the suite's train.py / evaluate.py runs share it (.ci/run sets
# one for both tiers).
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")  # "gw0", "gw1", ... in a pytest-xdist worker, else None
_OWN_CACHE = None
if "JAXTRAFFIC_COMPILATION_CACHE" not in os.environ:  # (a worker has its controller's, see pytest_configure)
    _OWN_CACHE = tempfile.mkdtemp(prefix="jaxtraffic-xla-cache-")
    os.environ["JAXTRAFFIC_COMPILATION_CACHE"] = _OWN_CACHE

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import tiny_runs  # noqa: E402

from jaxtraffic import TrafficParams, equilibrium  # noqa: E402
from jaxtraffic.model.solver import arz_step  # noqa: E402

# A tiny grid: 41 nodes (dx = 25 m), dt = 0.5 s, CFL ~ 0.072; fast to compile and run.
# (Coarser grids are not used: with the upwind inlet, node 0's speed obeys the locally unstable
# ODE v' = (V(q_in / v, h) - v) / tau_mix, held back only by the transport term |lambda2| / dx;
# at the defaults that needs dx < |lambda2| tau_mix / (1 / (q_in h_mix) - 1) ~ 35 m.)
SMALL = {"n_points": 41, "dt": 0.5}


@pytest.fixture
def x64():
    """Run the test with 64-bit floats enabled (locally, via the context manager)."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def small() -> TrafficParams:
    return TrafficParams(**SMALL)


def check_told_delay_run(out: Path, kind: str) -> None:
    """A trained run of a policy told the delay (a delay schedule, the residual on adaptive backstepping): it
    loads with ``load_policy``, is told 4 s (its training plant's delay), its summary holds ``kind``'s record,
    and told 2 s and 6 s in one batch on tiny plants it does not diverge in 20 steps."""
    from jaxtraffic import simulate_batch, stack_params
    from jaxtraffic.control import takes_delay, tell_delay
    from jaxtraffic.runs import load_policy

    ctrl, config = load_policy(out)
    assert takes_delay(ctrl) and float(ctrl.settings.delay) == config.plant.delay == 4.0
    assert f'"{kind}"' in (out / "summary.json").read_text()
    batch = tell_delay(ctrl, jnp.asarray([2.0, 6.0]))
    plants = stack_params(*(TrafficParams(n_points=21, delay=d) for d in (2.0, 6.0)))
    res = simulate_batch(plants, batch, n_steps=20, batch_controller=True)
    assert not np.any(np.asarray(res.metrics["diverged"]))


# The tiny training session (tiny_runs.py): started once, in the background, as soon as the tests
# are collected, each part only if a collected test needs it, so that it overlaps with the unit tests.
# JAXTRAFFIC_TEST_RUNS=DIR keeps its run directories in DIR, and a later pytest invocation with the
# same DIR reads them instead of training again (.ci/run: the slow tier reuses the default tier's).
_TRAINING: dict = {}
_NEEDS = {"two_devices": {"two_device_proc"}, "train": {"tiny_runs_root", "tiny_run_a"}}
_SHARED_ROOT = os.environ.get("JAXTRAFFIC_TEST_RUNS")
_OWN_ROOT = None  # the controlling process's shared directory for its workers (removed at its end)
_TRAINS = _WORKER in (None, "gw0")  # this process runs the training session (else it waits for it)


def pytest_configure(config):
    """In the controlling process of pytest-xdist workers: one training directory and one compilation cache
    for all of them (the workers inherit the environment)."""
    global _OWN_ROOT
    if _WORKER is None and getattr(config.option, "numprocesses", None) and not _SHARED_ROOT:
        _OWN_ROOT = tempfile.mkdtemp(prefix="jaxtraffic-tiny-runs-")
        os.environ["JAXTRAFFIC_TEST_RUNS"] = _OWN_ROOT


def _start_training(*parts: str) -> dict:
    if "root" not in _TRAINING:
        if _SHARED_ROOT:
            root = Path(_SHARED_ROOT)
            if _TRAINS and not (root / tiny_runs.DONE).exists():  # absent, or left by an interrupted session
                shutil.rmtree(root, ignore_errors=True)
            root.mkdir(parents=True, exist_ok=True)
        else:
            root = Path(tempfile.mkdtemp(prefix="jaxtraffic-tiny-runs-"))
        _TRAINING["root"] = root
    root = _TRAINING["root"]
    if "two_devices" in parts and "two_devices" not in _TRAINING:
        _TRAINING["two_devices"] = tiny_runs.start_two_devices()
    if "train" in parts and "train" not in _TRAINING:
        trains = _TRAINS and not (root / tiny_runs.DONE).exists()
        _TRAINING["train"] = tiny_runs.start_train_runs(root) if trains else None
    return _TRAINING


def pytest_collection_finish(session):
    used = set().union(*(getattr(item, "fixturenames", ()) for item in session.items))
    # under xdist every worker collects every test: the training starts in gw0 only (_TRAINS), and the
    # two-device run in the worker whose test asks for it
    parts = [part for part, fixtures in _NEEDS.items() if fixtures & used and (_WORKER is None or part == "train")]
    if parts:
        _start_training(*parts)


def pytest_sessionfinish(session, exitstatus):
    train = _TRAINING.get("train")
    if train is not None and train.poll() is None and _WORKER is not None and exitstatus == 0:
        try:  # another worker may still wait for these runs
            train.wait(timeout=900)
        except subprocess.TimeoutExpired:
            pass
    for name in ("two_devices", "train"):
        proc = _TRAINING.get(name)
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()
    if "root" in _TRAINING and not _SHARED_ROOT:
        shutil.rmtree(_TRAINING["root"], ignore_errors=True)
    if _OWN_ROOT:
        shutil.rmtree(_OWN_ROOT, ignore_errors=True)
    if _OWN_CACHE:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)
    if _WORKER is not None:
        _quiet_worker_exit()


def _quiet_worker_exit() -> None:
    """An xdist worker's last steps, made short and uninterruptible (issue 50, item 10).

    After this hook the worker reports "finished" and pytest then runs 5 garbage collections (its
    unraisable-exception check), each calling jax's GC callback over every compiled program the worker's
    tests left: many seconds on a loaded machine. execnet gives a worker 5 s once the controller closes it,
    then sends it SIGINT; the KeyboardInterrupt landed in jax's GC callback and the README's test command
    ended with a PytestUnraisableExceptionWarning. No test sends that signal: so jax's caches are dropped and
    collected here, before "finished", and the late SIGINT is ignored (the controller has every result;
    execnet still ends a worker that has not exited 10 s later)."""
    jax.clear_caches()
    gc.collect()
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.fixture(scope="session")
def two_device_proc():
    """The two-device training, running in a subprocess (``tiny_runs.TWO_DEVICES``)."""
    return _start_training("two_devices")["two_devices"]


@pytest.fixture(scope="session")
def tiny_runs_root() -> Path:
    """Directory holding the run directories ``tiny_runs.RUNS`` (waits until all are written)."""
    tr = _start_training("train")
    tiny_runs.wait_train_runs(tr["train"], tr["root"])
    return tr["root"]


@pytest.fixture(scope="session")
def tiny_run_a() -> Path:
    """Run A of the tiny training session, as soon as it is written (the other runs may still train)."""
    tr = _start_training("train")
    return tiny_runs.wait_run_a(tr["train"], tr["root"])


def bump_state(p: TrafficParams, amp_rho: float = 0.01, amp_v: float = 0.3, centre: float = 0.5,
               width: float = 0.1, dtype=jnp.float32) -> tuple[jax.Array, jax.Array]:
    """Equilibrium plus a smooth Gaussian bump (centre and width as fractions of L) in rho and v,
    with rho(0) = q_in / v(0) so that the inlet condition already holds."""
    rho_bar, v_bar = equilibrium(p)
    x = np.linspace(0.0, 1.0, p.n_points)
    g = np.exp(-(((x - centre) / width) ** 2))
    rho = float(rho_bar) + amp_rho * g
    v = float(v_bar) + amp_v * g
    rho[0] = float(p.q_in) / v[0]
    return jnp.asarray(rho, dtype), jnp.asarray(v, dtype)


def run_solver(rho: jax.Array, v: jax.Array, p: TrafficParams, n_steps: int, h: jax.Array | None = None):
    """``n_steps`` plain solver steps (jit + scan) at constant h (default h_bar).

    Returns (rho, v, mass_history, flux_history): mass M_n = dx * sum(rho_n[1:]) for n = 0..n_steps
    and (F_in, F_out) of each step.
    """
    h = jnp.full_like(rho, p.h_bar) if h is None else h

    @jax.jit
    def go(rho, v):
        def body(carry, _):
            r, u = carry
            r1, u1, f_in, f_out = arz_step(r, u, h, p)
            return (r1, u1), (p.dx * jnp.sum(r1[1:]), f_in, f_out)

        (r, u), (mass, f_in, f_out) = jax.lax.scan(body, (rho, v), None, length=n_steps)
        return r, u, jnp.concatenate([(p.dx * jnp.sum(rho[1:]))[None], mass]), (f_in, f_out)

    return go(rho, v)


def leaves_equal(a, b) -> bool:
    """Bitwise equality of two pytrees (NaN == NaN)."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    if len(la) != len(lb):
        return False
    return all(x == y if isinstance(x, str) or isinstance(y, str)  # (a checkpoint's config_problem)
               else np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in zip(la, lb, strict=True))


def take(tree, i: int):
    """Environment ``i`` of a batched pytree."""
    return jax.tree.map(lambda x: x[i], tree)
