"""Shared fixtures and helpers for the core test suite (tiny grids, a few hundred steps).

Precision: the library runs in float32 by default. Tests that need float64 (oracle digits, exact
mass balance, convergence order) use the ``x64`` fixture, which enables x64 only for the duration
of that test (``jax.enable_x64`` context manager), never globally.

Training: the suite trains once. ``tiny_runs_root`` (session scope) holds the run directories of the
one tiny training session (``tiny_runs.py``) that ``test_train.py`` reads; ``test_evaluate.py``
evaluates its run A (``tiny_run_a``). The session starts in the background right after collection.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

# The suite runs on ONE XLA device (as a user's program would with JAXTRAFFIC_NO_DEVICE_SPLIT=1),
# so that its figures do not depend on the machine's core count; the multi-device paths are tested
# in subprocesses that set their device count explicitly (tests/test_sharding.py, test_train.py).
os.environ.setdefault("JAXTRAFFIC_NO_DEVICE_SPLIT", "1")
# XLA's backend (LLVM) optimisation off in the test process unless XLA_FLAGS already chooses a level:
# it roughly halves compile time, which dominates these tiny-grid tests (-23 % CPU time measured on
# test_baselines + test_delay); the computed maths is the same programs' (comparisons are between
# programs of the same process). The training subprocesses of tiny_runs.py use it too.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest
import tiny_runs

from jaxtraffic import TrafficParams, equilibrium
from jaxtraffic.model.solver import arz_step

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


# The tiny training session (tiny_runs.py): started once, in the background, as soon as the tests
# are collected if a collected test needs it, so that it overlaps with the unit tests before it.
_TRAINING: dict = {}
_USES_TRAINING = {"two_device_proc", "tiny_runs_root", "tiny_run_a"}


def _start_training() -> dict:
    if not _TRAINING:
        root = Path(tempfile.mkdtemp(prefix="jaxtraffic-tiny-runs-"))
        _TRAINING.update(root=root, two_devices=tiny_runs.start_two_devices(),
                         train=tiny_runs.start_train_runs(root))
    return _TRAINING


def pytest_collection_finish(session):
    if any(_USES_TRAINING & set(getattr(item, "fixturenames", ())) for item in session.items):
        _start_training()


def pytest_sessionfinish(session, exitstatus):
    for name in ("two_devices", "train"):
        proc = _TRAINING.get(name)
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()
    if "root" in _TRAINING:
        shutil.rmtree(_TRAINING["root"], ignore_errors=True)


@pytest.fixture(scope="session")
def two_device_proc():
    """The two-device training, running in a subprocess (``tiny_runs.TWO_DEVICES``)."""
    return _start_training()["two_devices"]


@pytest.fixture(scope="session")
def tiny_runs_root() -> Path:
    """Directory holding the run directories ``tiny_runs.RUNS`` (waits until all are written)."""
    tr = _start_training()
    tiny_runs.wait_train_runs(tr["train"], tr["root"])
    return tr["root"]


@pytest.fixture(scope="session")
def tiny_run_a() -> Path:
    """Run A of the tiny training session, as soon as it is written (the other runs may still train)."""
    tr = _start_training()
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
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in zip(la, lb, strict=True))


def take(tree, i: int):
    """Environment ``i`` of a batched pytree."""
    return jax.tree.map(lambda x: x[i], tree)
