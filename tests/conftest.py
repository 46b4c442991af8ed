"""Shared fixtures and helpers for the core test suite (tiny grids, a few hundred steps).

Precision: the library runs in float32 by default. Tests that need float64 (oracle digits, exact
mass balance, convergence order) use the ``x64`` fixture, which enables x64 only for the duration
of that test (``jax.enable_x64`` context manager), never globally.
"""

from __future__ import annotations

import os

# The suite runs on ONE XLA device (as a user's program would with JAXTRAFFIC_NO_DEVICE_SPLIT=1),
# so that its figures do not depend on the machine's core count; the multi-device paths are tested
# in subprocesses that set their device count explicitly (tests/test_sharding.py, test_train.py).
os.environ.setdefault("JAXTRAFFIC_NO_DEVICE_SPLIT", "1")

import jax  # noqa: E402
import jax.numpy as jnp
import numpy as np
import pytest

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
