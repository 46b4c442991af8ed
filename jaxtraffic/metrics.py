"""Performance indices and norms (MODEL.md section 10), accumulated while a rollout streams.

Units: the J's use rho in veh/km, x in m, t in s (the paper's Table 2 magnitudes); speed in m/s,
acceleration a = v_t + v v_x in m/s^2. Space integrals use the trapezoidal rule over the nodes;
time integrals the left rectangle rule over the steps (sample at t_n, n = 0..n_steps-1), so a
uniform state of density rho over T seconds gives J_TTT = 1000 rho L T exactly.
The acceleration at t_n uses the forward difference (v^{n+1} - v^n)/dt; a_t at t_n is
(a^n - a^{n-1})/dt with a^{-1} := a^0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

Array = jax.Array

VEH_PER_KM = 1000.0  # veh/m -> veh/km
FUEL_B0, FUEL_B1, FUEL_B3, FUEL_B4 = 25e-3, 24.5e-6, 32.5e-9, 125e-6  # Treiber & Kesting
REWARD_TARGET = -0.1  # the paper's stop rule on the reward


def trapezoid(f: Array, dx: Array | float) -> Array:
    """Integral over [0, L] of nodal values ``f`` (last axis) by the trapezoidal rule."""
    return dx * (jnp.sum(f, axis=-1) - 0.5 * (f[..., 0] + f[..., -1]))


def spatial_gradient(u: Array, dx: Array | float) -> Array:
    """du/dx: central differences inside, one-sided at the two ends (units of u per m)."""
    inner = (u[2:] - u[:-2]) / (2.0 * dx)
    return jnp.concatenate([(u[1:2] - u[:1]) / dx, inner, (u[-1:] - u[-2:-1]) / dx])


def l2_deviation(u: Array, u_bar: Array | float) -> Array:
    """The paper's norm ||u - u_bar||_L2 = sqrt(mean_i (u_i - u_bar)^2), units of u."""
    return jnp.sqrt(jnp.mean((u - u_bar) ** 2, axis=-1))


def reward(rho: Array, v: Array, rho_bar: Array | float, v_bar: Array | float) -> Array:
    """Paper reward r = -sum_i [((rho_i - rho_bar)/rho_bar)^2 + ((v_i - v_bar)/v_bar)^2]."""
    return -jnp.sum(((rho - rho_bar) / rho_bar) ** 2 + ((v - v_bar) / v_bar) ** 2, axis=-1)


def fuel_rate(v: Array, a: Array) -> Array:
    """Fuel rate xi(v, a) = max(0, b0 + b1 v + b3 v^3 + b4 v a), in ml/s per vehicle."""
    return jnp.maximum(0.0, FUEL_B0 + FUEL_B1 * v + FUEL_B3 * v**3 + FUEL_B4 * v * a)


@struct.dataclass
class MetricsAccumulator:
    """Running sums of one rollout. All scalars except ``a_prev`` (shape (n,))."""

    J_TTT: Array
    J_fuel: Array
    J_comfort: Array
    effort_sq: Array  # sum over steps of mean_i (h_sent - h_bar)^2, s^2
    n_active: Array  # number of accumulated (healthy) steps
    last_bad_step: Array  # last step index whose reward was below REWARD_TARGET (-1: none)
    max_cfl: Array
    a_prev: Array


def init_metrics(n_points: int, dtype=jnp.float32) -> MetricsAccumulator:
    z = jnp.zeros((), dtype)
    return MetricsAccumulator(
        J_TTT=z, J_fuel=z, J_comfort=z, effort_sq=z, n_active=jnp.zeros((), jnp.int32),
        last_bad_step=jnp.full((), -1, jnp.int32), max_cfl=z, a_prev=jnp.full((n_points,), jnp.nan, dtype),
    )


def update_metrics(
    acc: MetricsAccumulator, *, step: Array, rho: Array, v: Array, v_next: Array, h_sent: Array,
    rho_bar: Array, v_bar: Array, h_bar: Array | float, dx: Array | float, dt: Array | float,
    cfl: Array, active: Array,
) -> MetricsAccumulator:
    """Add the contribution of step ``step`` (state at t_n, speed at t_{n+1}) if ``active``."""
    a = (v_next - v) / dt + v * spatial_gradient(v, dx)
    a_prev = jnp.where(jnp.isnan(acc.a_prev), a, acc.a_prev)
    a_t = (a - a_prev) / dt
    rho_km = VEH_PER_KM * rho
    w = jnp.where(active, dt, 0.0)
    r = reward(rho, v, rho_bar, v_bar)
    return MetricsAccumulator(
        J_TTT=acc.J_TTT + w * trapezoid(rho_km, dx),
        J_fuel=acc.J_fuel + w * trapezoid(fuel_rate(v, a) * rho_km, dx),
        J_comfort=acc.J_comfort + w * trapezoid((a**2 + a_t**2) * rho_km, dx),
        effort_sq=acc.effort_sq + jnp.where(active, jnp.mean((h_sent - h_bar) ** 2), 0.0),
        n_active=acc.n_active + active.astype(jnp.int32),
        last_bad_step=jnp.where(active & (r < REWARD_TARGET), step, acc.last_bad_step),
        max_cfl=jnp.where(active, jnp.maximum(acc.max_cfl, cfl), acc.max_cfl),
        a_prev=jnp.where(active, a, acc.a_prev),
    )
