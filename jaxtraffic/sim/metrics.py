"""Performance indices and norms (docs/model.md section 10), accumulated while a rollout streams.

Units: the state is SI (rho in veh/m), every density metric veh/km: the J's use rho in veh/km, x in m, t in s
(the paper's Table 2 magnitudes), the density norms (``density_l2``, ``density_std``) are in veh/km; speed in m/s,
acceleration a = v_t + v v_x in m/s^2. Space integrals use the trapezoidal rule over the nodes;
time integrals the left rectangle rule over the steps (sample at t_n, n = 0..n_steps-1), so a
uniform state of density rho over T seconds gives J_TTT = 1000 rho L T (to rounding). The time
sums are kept per node during the rollout and integrated in space once at the end.
The acceleration at t_n uses the forward difference (v^{n+1} - v^n)/dt; a_t at t_n is
(a^n - a^{n-1})/dt with a^{-1} := a^0.

Two readings of the integrands (docs/model.md section 10): **SI** (above; the library's own) and
the **paper's** (speeds in km/h inside the integrands: a and a_t x 3.6, so the comfort parts are
KMH^2 = 12.96 x the SI ones, and xi(3.6 v, 3.6 a) with the same b_i; rho in veh/km, x in m, t in s
in both). J_comfort is also kept as its parts a^2 and a_t^2, and the a_t^2 contribution of the
*switch-on step* (the step n = d = D/dt at which the first controlled input reaches the plant;
at D = 0 it is step 0, whose a_t is 0 by the a^{-1} := a^0 rule), so that J_comfort without the
switch-on spike is defined the same way for every controller and delay.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any, NamedTuple, cast

import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.model.fundamental import in_physical_region

Array = jax.Array

VEH_PER_KM = 1000.0  # veh/m (the state's unit, SI) -> veh/km (the unit of every density metric and output)
FUEL_B0, FUEL_B1, FUEL_B3, FUEL_B4 = 25e-3, 24.5e-6, 32.5e-9, 125e-6  # Treiber & Kesting
KMH = 3.6  # m/s -> km/h
REWARD_TARGET = -0.1  # the paper's stop rule on the reward
# veh/km: a plant of the robustness map is *stabilised* when it did not diverge and the spatial standard
# deviation of its final density (the remaining waves, blind to a uniform offset) is below this
STABLE_STD = 0.5
REWARD_DX = 5.0  # m, the paper's grid spacing: the reward's per-node sum is weighted by dx / REWARD_DX
LATE_WINDOW_S = 150.0  # s: the late window of "late_max_rho_std" (the last 150 s of a rollout)


def trapezoid(f: Array, dx: Array | float) -> Array:
    """Integral over [0, L] of nodal values ``f`` (last axis) by the trapezoidal rule."""
    return dx * (jnp.sum(f, axis=-1) - 0.5 * (f[..., 0] + f[..., -1]))


def spatial_gradient(u: Array, dx: Array | float) -> Array:
    """du/dx: central differences inside, one-sided at the two ends (units of u per m)."""
    inv_dx = 1.0 / dx
    inner = (u[2:] - u[:-2]) * (0.5 * inv_dx)
    return jnp.concatenate([(u[1:2] - u[:1]) * inv_dx, inner, (u[-1:] - u[-2:-1]) * inv_dx])


def l2_deviation(u: Array, u_bar: Array | float) -> Array:
    """The paper's norm ||u - u_bar||_L2 = sqrt(mean_i (u_i - u_bar)^2), units of u."""
    return jnp.sqrt(jnp.mean((u - u_bar) ** 2, axis=-1))


def density_l2(rho: Array, rho_bar: Array | float) -> Array:
    """||rho - rho_bar||_L2 (``l2_deviation``) in veh/km of densities in veh/m: the unit of every density metric."""
    return VEH_PER_KM * l2_deviation(rho, rho_bar)


def density_std(rho: Array) -> Array:
    """The standard deviation over x (last axis) of densities in veh/m, in veh/km (the waves left, blind to a
    uniform offset)."""
    return VEH_PER_KM * jnp.std(rho, axis=-1)


def node_weight(dx: Array | float) -> Array | float:
    """dx / ``REWARD_DX``: the weight of one node in the paper's per-node sums (1 on the paper's grid),
    so that a sum over nodes approximates the same integral, (1/5 m) int (...) dx, on every grid."""
    return dx * (1.0 / REWARD_DX)


def reward(rho: Array, v: Array, rho_bar: Array | float, v_bar: Array | float, dx: Array | float) -> Array:
    """Paper reward r = -(dx / 5 m) sum_i [((rho_i - rho_bar)/rho_bar)^2 + ((v_i - v_bar)/v_bar)^2]
    (dimensionless; the paper's per-node sum on its 5 m grid, the same integral on any other)."""
    terms = ((rho - rho_bar) * (1.0 / rho_bar)) ** 2 + ((v - v_bar) * (1.0 / v_bar)) ** 2
    return -jnp.sum(terms, axis=-1) * node_weight(dx)


def physical_reward(rho: Array, v: Array, rho_bar: Array | float, v_bar: Array | float,
                    l: Array | float, dx: Array | float) -> Array:
    """The reward of (rho, v), or NaN if any node is outside the physical region
    (finite, 0 < rho < 1/l, v >= 0): one reduction serves both the divergence check and the reward."""
    ok = in_physical_region(rho, v, l)
    terms = ((rho - rho_bar) * (1.0 / rho_bar)) ** 2 + ((v - v_bar) * (1.0 / v_bar)) ** 2
    return -jnp.sum(jnp.where(ok, terms, jnp.nan), axis=-1) * node_weight(dx)


def material_acceleration(v: Array, v_next: Array, dx: Array | float, dt: Array | float) -> Array:
    """a = v_t + v v_x at t_n (m/s^2): forward difference in time, ``spatial_gradient`` in space."""
    return (v_next - v) * (1.0 / dt) + v * spatial_gradient(v, dx)


def fuel_rate(v: Array | float, a: Array | float) -> Array:
    """Fuel rate xi(v, a) = max(0, b0 + b1 v + b3 v^3 + b4 v a), in ml/s per vehicle."""
    return jnp.maximum(0.0, FUEL_B0 + FUEL_B1 * v + FUEL_B3 * v**3 + FUEL_B4 * v * a)


def fuel_rate_kmh(v: Array | float, a: Array | float) -> Array:
    """The paper's reading of xi: ``fuel_rate`` with the speed in km/h and the acceleration in
    km/h/s (v, a given in SI: m/s, m/s^2)."""
    return fuel_rate(KMH * v, KMH * a)


@struct.dataclass
class MetricsAccumulator:
    """Running sums of one rollout, kept *per grid node* (shape (n,)) so that the streaming
    update is purely elementwise (it fuses with the solver step; no spatial reduction per step).
    The spatial integrals are taken once, at the end (``totals``): by linearity,
    sum_n dt trapz(f^n) = trapz(sum_n dt f^n).

    J_TTT, J_fuel, J_comfort: time integrals of the integrands at each node (rho in veh/km).
    effort_sq: sum over steps of (h_sent - h_bar)^2, s^2.
    max_cfl: max over steps of the CFL number max(|lambda1|, |lambda2|) dt/dx at each node.
    a_prev: the previous step's acceleration, m/s^2.
    J_comfort_a2, J_comfort_at2: the a^2 and a_t^2 parts of J_comfort (SI).
    J_comfort_switch: the a_t^2 part at the switch-on step (``switch_step``; SI).
    J_fuel_kmh: J_fuel with ``fuel_rate_kmh`` (the paper's reading).
    n_active (scalar): number of accumulated (healthy) steps.
    last_bad_step (scalar): last step index whose reward was below REWARD_TARGET (-1: none).
    late_max_rho_std (scalar): max of std_x(rho) (veh/m; ``late_max`` reports it in veh/km) over the healthy steps
    n >= ``MetricsTarget.late_step``
    (an opt-in metric, ``OPTIONAL_METRICS``: not in the default selection).
    A field is None when the rollout's metrics do not read it (``init_metrics(keep=...)``, ``accumulators``).
    """

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> MetricsAccumulator: ...

    J_TTT: Array
    J_fuel: Array
    J_comfort: Array
    effort_sq: Array
    max_cfl: Array
    a_prev: Array
    n_active: Array
    last_bad_step: Array
    J_comfort_a2: Array
    J_comfort_at2: Array
    J_comfort_switch: Array
    J_fuel_kmh: Array
    late_max_rho_std: Array


def init_metrics(n_points: int, dtype=jnp.float32, keep: Iterable[str] | None = None) -> MetricsAccumulator:
    """Zero sums for ``n_points`` nodes; only the fields named in ``keep`` (default: all; see
    ``accumulators``), the others None, so that ``update_metrics`` neither computes nor carries them."""
    z = jnp.zeros((n_points,), dtype)
    full = dict(
        J_TTT=z, J_fuel=z, J_comfort=z, effort_sq=z, max_cfl=z, a_prev=z,
        n_active=jnp.zeros((), jnp.int32), last_bad_step=jnp.full((), -1, jnp.int32),
        J_comfort_a2=z, J_comfort_at2=z, J_comfort_switch=z, J_fuel_kmh=z, late_max_rho_std=jnp.zeros((), dtype),
    )
    kept = full.keys() if keep is None else set(keep)
    return MetricsAccumulator(**cast(dict[str, Any], {k: (v if k in kept else None) for k, v in full.items()}))


class StepRecord(NamedTuple):
    """What one step contributes to the metrics (step n: the state at t_n, the speed at t_{n+1}).

    step: the step index n (int32 scalar).
    rho, v: the state at t_n, veh/m and m/s, shape (n_points,).
    v_next: the speed at t_{n+1}, m/s, shape (n_points,).
    h_sent: the time gap sent at step n, s, shape (n_points,).
    cfl: the CFL number max(|lambda1|, |lambda2|) dt/dx of the step, per node (n_points,) or a scalar.
    active: whether the step counts (bool scalar; False once the plant diverged).
    reward_next: the reward of the state at t_{n+1} (dimensionless scalar), or None to compute the
        reward of the state at t_n here.
    """

    step: Array
    rho: Array
    v: Array
    v_next: Array
    h_sent: Array
    cfl: Array | float
    active: Array
    reward_next: Array | None = None


class MetricsTarget(NamedTuple):
    """The constants of a rollout's metrics: the target equilibrium rho_bar (veh/m), v_bar (m/s) and
    h_bar (s), the grid spacing dx (m), the time step dt (s) and the switch-on step ``switch_step``
    (the plant's delay in steps: the step whose a_t^2 is the switch-on spike); ``late_step``: the first step of
    the late window of ``late_max_rho_std`` (n_steps - ``late_steps(dt)`` in a rollout; 0: every step)."""

    rho_bar: Array | float
    v_bar: Array | float
    h_bar: Array | float
    dx: Array | float
    dt: Array | float
    switch_step: Array | int = 0
    late_step: Array | int = 0


def update_metrics(acc: MetricsAccumulator, record: StepRecord, target: MetricsTarget) -> MetricsAccumulator:
    """Add the contribution of step ``record.step`` (state at t_n, speed at t_{n+1}) if ``record.active``.

    Args:
        acc: the running sums (per node).
        record: the step's quantities (``StepRecord``).
        target: the rollout's constants (``MetricsTarget``).
    Returns:
        The updated sums. Inactive steps add exactly zero (``where``, not a multiplication, so a
        non-finite value never enters).

    ``last_bad_step`` follows the reward of the state at t_n (index ``step``), or, when
    ``record.reward_next`` is given, the reward of the state at t_{n+1} (index ``step + 1``; the
    caller then counts the initial state itself).
    """
    step, rho, v, v_next, h_sent, cfl, active, reward_next = record
    rho_bar, v_bar, h_bar, dx, dt, switch_step, late_step = target
    inv_dt = 1.0 / dt
    a = material_acceleration(v, v_next, dx, dt)
    a_prev = jnp.where(step == 0, a, acc.a_prev) if acc.a_prev is not None else None
    a_t = (a - a_prev) * inv_dt if a_prev is not None else None
    w = (dt * VEH_PER_KM) * rho

    def add(total, inc):
        return total + jnp.where(active, inc, 0.0)

    def last_bad():
        if reward_next is None:
            r, r_step = reward(rho, v, rho_bar, v_bar, dx), step
        else:
            r, r_step = reward_next, step + 1
        return jnp.where(active & (r < REWARD_TARGET), r_step, acc.last_bad_step)

    def at2():
        return a_t * a_t * w

    # each kept field's new value (a field left out of ``init_metrics`` stays None: not computed)
    new = {
        "J_TTT": lambda: add(acc.J_TTT, w),
        "J_fuel": lambda: add(acc.J_fuel, fuel_rate(v, a) * w),
        "J_comfort": lambda: add(acc.J_comfort, (a * a + a_t * a_t) * w),
        "effort_sq": lambda: add(acc.effort_sq, (h_sent - h_bar) ** 2),
        "max_cfl": lambda: jnp.where(active, jnp.maximum(acc.max_cfl, cfl), acc.max_cfl),
        "a_prev": lambda: jnp.where(active, a, acc.a_prev),
        "n_active": lambda: acc.n_active + active.astype(jnp.int32),
        "last_bad_step": last_bad,
        "J_comfort_a2": lambda: add(acc.J_comfort_a2, a * a * w),
        "J_comfort_at2": lambda: add(acc.J_comfort_at2, at2()),
        "J_comfort_switch": lambda: add(acc.J_comfort_switch, jnp.where(step == switch_step, at2(), 0.0)),
        "J_fuel_kmh": lambda: add(acc.J_fuel_kmh, fuel_rate_kmh(v, a) * w),
        "late_max_rho_std": lambda: jnp.where(active & (step >= late_step),
                                              jnp.maximum(acc.late_max_rho_std, jnp.std(rho)), acc.late_max_rho_std),
    }
    return MetricsAccumulator(**cast(dict[str, Any], {k: (None if getattr(acc, k) is None else f())
                                                      for k, f in new.items()}))


def totals(acc: MetricsAccumulator, dx: Array | float) -> dict[str, Array]:
    """Scalar indices from the per-node sums: J_TTT, J_fuel, J_comfort (trapezoid in space),
    control_effort (RMS of h_sent - h_bar over space and active steps, s) and max_cfl, then
    the comfort parts and the paper's (km/h) reading (``EXTRA_INDICES``); only those whose sums
    ``acc`` keeps (``METRIC_ACCUMULATORS``)."""
    def trap(name):
        return lambda: trapezoid(getattr(acc, name), dx)

    a2, at2, sw = trap("J_comfort_a2"), trap("J_comfort_at2"), trap("J_comfort_switch")
    k2 = KMH * KMH
    table = {
        "J_TTT": trap("J_TTT"),
        "J_fuel": trap("J_fuel"),
        "J_comfort": trap("J_comfort"),
        "control_effort": lambda: jnp.sqrt(jnp.mean(acc.effort_sq) / jnp.maximum(acc.n_active, 1)),
        "max_cfl": lambda: jnp.max(acc.max_cfl),
        "J_comfort_a2": a2, "J_comfort_at2": at2, "J_comfort_switch_on": sw,
        "J_comfort_no_switch_on": lambda: a2() + at2() - sw(),
        "J_TTT_kmh": trap("J_TTT"),
        "J_fuel_kmh": trap("J_fuel_kmh"),
        "J_comfort_kmh": lambda: k2 * (a2() + at2()),
        "J_comfort_a2_kmh": lambda: k2 * a2(), "J_comfort_at2_kmh": lambda: k2 * at2(),
        "J_comfort_switch_on_kmh": lambda: k2 * sw(),
        "J_comfort_no_switch_on_kmh": lambda: k2 * (a2() + at2() - sw()),
    }
    return {k: f() for k, f in table.items() if kept(acc, k)}


def kept(acc: MetricsAccumulator, metric: str) -> bool:
    """Whether ``acc`` keeps every running sum that ``metric`` reads."""
    return all(getattr(acc, f) is not None for f in METRIC_ACCUMULATORS[metric])


# The extra indices of ``totals`` (besides J_TTT, J_fuel, J_comfort, control_effort, max_cfl).
EXTRA_INDICES = ("J_comfort_a2", "J_comfort_at2", "J_comfort_switch_on", "J_comfort_no_switch_on",
                 "J_TTT_kmh", "J_fuel_kmh", "J_comfort_kmh", "J_comfort_a2_kmh", "J_comfort_at2_kmh",
                 "J_comfort_switch_on_kmh", "J_comfort_no_switch_on_kmh")


# Every metric of a rollout (``sim.rollout.finalize_metrics``, in its order) -> the running sums of
# ``MetricsAccumulator`` it reads (the final-state ones read none).
_COMFORT3 = ("J_comfort_a2", "J_comfort_at2", "J_comfort_switch")
METRIC_ACCUMULATORS: dict[str, tuple[str, ...]] = {
    "J_TTT": ("J_TTT",), "J_fuel": ("J_fuel",), "J_comfort": ("J_comfort",),
    "final_rho_L2": (), "final_v_L2": (), "final_reward": (), "time_to_reward_target_s": ("last_bad_step",),
    "diverged": (), "diverged_at_s": (), "diverged_reason": (),
    "control_effort": ("effort_sq", "n_active"), "max_cfl": ("max_cfl",),
    "J_comfort_a2": ("J_comfort_a2",), "J_comfort_at2": ("J_comfort_at2",),
    "J_comfort_switch_on": ("J_comfort_switch",),
    "J_comfort_no_switch_on": _COMFORT3, "J_TTT_kmh": ("J_TTT",), "J_fuel_kmh": ("J_fuel_kmh",),
    "J_comfort_kmh": _COMFORT3[:2], "J_comfort_a2_kmh": ("J_comfort_a2",), "J_comfort_at2_kmh": ("J_comfort_at2",),
    "J_comfort_switch_on_kmh": ("J_comfort_switch",), "J_comfort_no_switch_on_kmh": _COMFORT3,
    "late_max_rho_std": ("late_max_rho_std",),
}
# the metrics computed only when asked for (not in the default selection, ``select_metrics(None)``)
OPTIONAL_METRICS: tuple[str, ...] = ("late_max_rho_std",)
METRIC_NAMES: tuple[str, ...] = tuple(k for k in METRIC_ACCUMULATORS if k not in OPTIONAL_METRICS)
# the sums that need the previous step's acceleration (a_t)
_NEED_A_PREV = frozenset(("J_comfort", "J_comfort_at2", "J_comfort_switch"))


def select_metrics(names: Iterable[str] | str | None) -> tuple[str, ...]:
    """The metrics a caller asks for, in ``METRIC_NAMES`` order (a hashable, canonical static argument):
    None: all of them but ``OPTIONAL_METRICS``; a string: that one metric; any other iterable of names (possibly
    empty: no metrics). Raises ValueError for a name that is not a metric, listing the valid ones."""
    if names is None:
        return METRIC_NAMES
    asked = {names} if isinstance(names, str) else set(names)
    unknown = sorted(str(n) for n in asked - set(METRIC_ACCUMULATORS))
    if unknown:
        raise ValueError(f"unknown metric(s) {unknown}; the metrics are: {', '.join(METRIC_ACCUMULATORS)}")
    return tuple(n for n in METRIC_ACCUMULATORS if n in asked)


def late_steps(dt: Array | float) -> Array:
    """The number of steps of ``dt`` (s) in ``LATE_WINDOW_S`` (int32)."""
    return jnp.round(LATE_WINDOW_S / dt).astype(jnp.int32)


def late_max(acc: MetricsAccumulator, rho_final: Array, diverged: Array) -> Array:
    """The "late_max_rho_std" metric (veh/km): the accumulated late maximum of std_x(rho) (kept in veh/m) and the
    final state's; +inf for a diverged rollout."""
    return jnp.where(diverged, jnp.inf, VEH_PER_KM * jnp.maximum(acc.late_max_rho_std, jnp.std(rho_final)))


def accumulators(names: Iterable[str]) -> frozenset[str]:
    """The ``MetricsAccumulator`` fields that the metrics ``names`` need (``a_prev`` where a_t is read)."""
    fields = {f for n in names for f in METRIC_ACCUMULATORS[n]}
    return frozenset(fields | ({"a_prev"} if fields & _NEED_A_PREV else set()))
