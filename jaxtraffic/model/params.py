"""Model parameters, numerical grid and the uniform equilibrium (docs/model.md sections 1-2, 4).

``TrafficParams`` is a ``flax.struct`` pytree. Its float fields (physical constants, the plant's
input delay, the time step) are *traced*: a batch of scenarios is a ``vmap`` over a batched
``TrafficParams`` and changing them never recompiles. Its shape-setting fields (``n_points``,
``max_delay_steps``) and the choice of ``scheme`` are *static* (part of the tree structure), so
changing them compiles a new program, as it must.

Validation runs whenever a ``TrafficParams`` is built from concrete numbers (never on tracers),
so invalid input fails at construction with a clear message.
"""

from __future__ import annotations

import math
import numbers
from typing import TYPE_CHECKING, Any, TypeGuard, cast

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxtraffic.fields import hyper
from jaxtraffic.model import fundamental
from jaxtraffic.model.schemes import SCHEME_NAMES
from jaxtraffic.platform.tracing import concrete

SCHEMES = SCHEME_NAMES  # model.schemes.SCHEMES maps each name to its composed pieces
FLOAT_FIELDS = ("L", "l", "q_in", "alpha", "tau_acc", "tau_m", "h_bar", "h_m", "delay", "dt", "h_min", "h_max",
                "alpha_noise")
MODELS = ("arz", "linear")
# the reference plant's grid (``TrafficParams.reference``): the coarsest level of the convergence study
# (benchmarks/convergence_study.py) at which every convergent metric of every closed loop is within 5 % of the
# next finer level's but the shock-carrying Lyapunov loop's speed L2 (docs/model.md section 15.2)
REFERENCE_POINTS, REFERENCE_SUBSTEPS = 801, 2


@struct.dataclass
class TrafficParams:
    """Plant and grid parameters; defaults are the paper's Table 1 and section 4.2 grid.

    Attributes (units):
        L: road length, m.              l: effective vehicle length, m.
        q_in: inflow, veh/s (1200 veh/h = 1/3 veh/s).
        alpha: ACC penetration rate in [0, 1].
        tau_acc, tau_m: relaxation times of ACC and manual vehicles, s.
        h_bar: nominal ACC time gap, s.  h_m: manual time gap, s.
        delay: plant input delay D, s (a non-negative multiple of ``dt``).
        dt: time step, s.
        h_min, h_max: actuator bounds on the ACC time gap, s.
        alpha_noise: std of Gaussian noise added to the plant's alpha, redrawn every step
            (clipped to [0, 1]); 0 disables it.
        n_points: number of grid points (static); dx = L / (n_points - 1).
        substeps: solver steps per time step (static, >= 1): the plant advances ``dt`` in
            ``substeps`` explicit steps of dt / substeps, while the control period, the delay
            buffer and the indices' sampling stay at ``dt`` (a finer plant without a faster controller).
        max_delay_steps: capacity of the input-delay ring buffer in steps (static).
        scheme: ``"upwind"`` (first order, the paper's method) or ``"muscl"`` (second order,
            minmod-limited reconstruction with SSP-RK2 time stepping) (static).
        model: plant model, ``"arz"`` (nonlinear, the default) or ``"linear"`` (the
            linearisation of docs/model.md section 6 on the same grid, for tests and design) (static).
    """

    if TYPE_CHECKING:  # added by flax.struct.dataclass (dataclasses.replace), which its stub omits
        def replace(self, **changes: Any) -> TrafficParams: ...

    L: float = 1000.0
    l: float = 5.0
    q_in: float = 1.0 / 3.0
    # a field with a help text is also a flag of train.py (``jaxtraffic.fields``); the others are set in a run's
    # config file ([plant] table)
    alpha: float = hyper(0.15, lo=0.0, hi=1.0, help="ACC penetration rate")
    tau_acc: float = 2.0
    tau_m: float = 60.0
    h_bar: float = 1.5
    h_m: float = 1.0
    delay: float = hyper(0.0, lo=0.0, help="plant input delay D, s (multiple of dt)")
    dt: float = hyper(0.1, lo=0.0, lo_open=True, help="time step, s (the control period)")
    h_min: float = 0.5
    h_max: float = 3.0
    alpha_noise: float = hyper(0.0, lo=0.0, help="per-step std of plant alpha noise")
    n_points: int = hyper(201, lo=3, static=True, help="grid points (dx = L/(n-1))")
    substeps: int = hyper(1, lo=1, static=True, help="solver steps per time step dt")
    max_delay_steps: int = hyper(100, lo=0, hi=10**6, static=True, help="delay buffer capacity, steps")
    scheme: str = hyper("upwind", static=True, help="the plant's numerical scheme (upwind: the paper's; muscl: "
                        "second order)", choices=SCHEMES)
    model: str = struct.field(pytree_node=False, default="arz")

    def __post_init__(self) -> None:
        for name in ("n_points", "substeps", "max_delay_steps"):  # numpy integers are ints too (np.int64(21))
            value = getattr(self, name)
            if isinstance(value, numbers.Integral) and not isinstance(value, (bool, int)):
                object.__setattr__(self, name, int(value))
        check_params(self)

    @classmethod
    def reference(cls, **changes: Any) -> TrafficParams:
        """The reference plant: the paper's road on the discretisation at which the closed-loop results no
        longer depend on the grid (docs/model.md section 15): MUSCL, 801 points (dx = 1.25 m), dt = 0.1 s
        in 2 solver steps. ``changes``: other fields (delay, alpha, ...)."""
        return cls(**{"n_points": REFERENCE_POINTS, "scheme": "muscl", "substeps": REFERENCE_SUBSTEPS, **changes})

    @property
    def dx(self) -> jax.Array | float:
        """Grid spacing, m."""
        return self.L / (self.n_points - 1)

    @property
    def solver_dt(self) -> jax.Array | float:
        """Time step of the solver, s: dt / substeps."""
        return self.dt / self.substeps if self.substeps != 1 else self.dt

    @property
    def delay_steps(self) -> jax.Array:
        """Plant delay in steps, d = round(D / dt), as an int32 (traced)."""
        return jnp.round(jnp.asarray(self.delay) / self.dt).astype(jnp.int32)

    def x(self) -> jax.Array:
        """Grid point positions x_i = i dx, m, shape (n_points,)."""
        return jnp.linspace(0.0, 1.0, self.n_points) * self.L


def params_valid(p: TrafficParams) -> jax.Array:
    """Whether the (possibly traced) parameters are usable, as a boolean array: the range checks of
    ``check_params`` that can be done inside a program (every float finite, lengths and times > 0, alpha in
    [0, 1], alpha_noise >= 0, h_min < h_bar <= h_max... , 0 <= delay <= max_delay_steps dt). ``sim.plant``
    freezes a plant whose parameters fail it at step 0 (``sim.outcome.Divergence.PARAMS``) instead of running a
    different system."""
    f = {k: jnp.asarray(getattr(p, k), jnp.float32) for k in FLOAT_FIELDS}
    ok = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in f.values()]))
    for name in ("L", "l", "q_in", "tau_acc", "tau_m", "h_bar", "h_m", "dt", "h_min"):
        ok &= jnp.all(f[name] > 0)
    ok &= jnp.all((f["alpha"] >= 0) & (f["alpha"] <= 1)) & jnp.all(f["alpha_noise"] >= 0)
    ok &= jnp.all(f["h_max"] > f["h_min"]) & jnp.all((f["h_bar"] >= f["h_min"]) & (f["h_bar"] <= f["h_max"]))
    d = jnp.round(f["delay"] / f["dt"])
    return ok & jnp.all(f["delay"] >= 0) & jnp.all(d <= p.max_delay_steps)


def check_params(p: TrafficParams, cfl_max: float = 1.0) -> None:
    """Raise ``ValueError`` with a clear message if concrete parameters are invalid.

    Checks positivity of lengths and times, alpha in [0, 1], actuator bounds, that the inflow
    admits an equilibrium, that the delay is a non-negative multiple of dt within the buffer's
    capacity, and the CFL condition max|lambda| (dt/substeps)/dx <= ``cfl_max`` over the actuator
    range (``cfl_bound``).
    Fields that are traced (inside ``jit``/``vmap``) are skipped: validate before tracing.
    """
    if isinstance(p.n_points, bool) or not isinstance(p.n_points, int) or p.n_points < 3:
        raise ValueError(f"n_points must be an int >= 3, got {p.n_points!r}")
    if isinstance(p.substeps, bool) or not isinstance(p.substeps, int) or p.substeps < 1:
        raise ValueError(f"substeps must be an int >= 1, got {p.substeps!r}")
    if isinstance(p.max_delay_steps, bool) or not isinstance(p.max_delay_steps, int) or p.max_delay_steps < 0:
        raise ValueError(f"max_delay_steps must be an int >= 0, got {p.max_delay_steps!r}")
    if p.scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, got {p.scheme!r}")
    if p.model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {p.model!r}")
    for name in FLOAT_FIELDS:
        value = getattr(p, name)
        if isinstance(value, (str, bytes)):
            raise ValueError(f"{name} must be a number, got {value!r}")
    found = {k: concrete(getattr(p, k), jax_arrays=False) for k in FLOAT_FIELDS}
    vals = {k: v for k, v in found.items() if v is not None}
    if len(vals) < len(found):
        return  # traced or placeholder leaves: nothing concrete to check
    for name, v in vals.items():
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be finite, got {v}")
    for name in ("L", "l", "q_in", "tau_acc", "tau_m", "h_bar", "h_m", "dt", "h_min"):
        if not np.all(vals[name] > 0):
            raise ValueError(f"{name} must be > 0, got {vals[name]}")
    if not np.all((vals["alpha"] >= 0) & (vals["alpha"] <= 1)):
        raise ValueError(f"alpha must lie in [0, 1], got {vals['alpha']}")
    if not np.all(vals["alpha_noise"] >= 0):
        raise ValueError(f"alpha_noise must be >= 0, got {vals['alpha_noise']}")
    if not np.all(vals["h_max"] > vals["h_min"]):
        raise ValueError(f"need h_max > h_min, got {vals['h_min']}, {vals['h_max']}")
    if not np.all((vals["h_bar"] >= vals["h_min"]) & (vals["h_bar"] <= vals["h_max"])):
        raise ValueError(f"h_bar {vals['h_bar']} outside actuator bounds [{vals['h_min']}, {vals['h_max']}]")
    hm_bar = _h_mix_np(vals["h_bar"], vals)
    if not np.all(1.0 / vals["q_in"] > hm_bar):
        raise ValueError(
            f"inflow q_in={vals['q_in']} veh/s has no equilibrium: need 1/q_in > h_mix(h_bar)"
            f" = {hm_bar} s (q_in < {1.0 / hm_bar} veh/s)")
    d = vals["delay"] / vals["dt"]
    if not np.all(vals["delay"] >= 0) or not np.allclose(d, np.round(d), rtol=0, atol=1e-4):
        raise ValueError(f"delay must be a non-negative multiple of dt={vals['dt']} s, got {vals['delay']}")
    if not np.all(np.round(d) <= p.max_delay_steps):
        raise ValueError(
            f"delay {vals['delay']} s is {int(np.max(np.round(d)))} steps, above the buffer capacity"
            f" max_delay_steps={p.max_delay_steps}; raise max_delay_steps")
    cfl = _cfl_bound_np(vals, p.n_points, p.substeps)
    if not cfl <= cfl_max:
        dx = vals["L"] / (p.n_points - 1)
        raise ValueError(
            f"CFL violated: max|lambda| dt/dx = {cfl:.3f} > {cfl_max} over the actuator range h in [h_min, h_max]"
            f" (solver step dt/substeps = {np.max(vals['dt']) / p.substeps:g} s, dx = {dx:g} m): at h = h_min the"
            f" speed characteristic lambda2 = v - 1/(rho h_mix(h)) is fastest; raise substeps, reduce dt or use"
            " fewer points")


def check_nominal(plant: TrafficParams, nominal: TrafficParams | None) -> None:
    """Raise ``ValueError`` unless ``nominal`` (the controller's model and the metrics' target) is on
    the plant's grid: the same n_points, dt and L (so dx). The controller's step counts, its
    predictor's dx and dt and the metrics' times all use the nominal's, so a nominal on another grid
    gives silently wrong results. Traced values are not checked."""
    if nominal is None:
        return
    if nominal.n_points != plant.n_points:
        raise ValueError(f"nominal.n_points={nominal.n_points} differs from the plant's n_points={plant.n_points}: "
                         "the nominal must be on the plant's grid")
    for name in ("dt", "L"):
        a = concrete(getattr(plant, name), jax_arrays=False)
        b = concrete(getattr(nominal, name), jax_arrays=False)
        if a is None or b is None:
            continue
        if not np.allclose(a, b, rtol=1e-6, atol=0.0):
            raise ValueError(f"nominal.{name}={b.tolist()} differs from the plant's {name}={a.tolist()}: the nominal "
                             f"must be on the plant's grid (same n_points, dt and L); change the nominal's "
                             f"physical constants only")


def check_steps(n_steps: object, record_every: object = 0) -> None:
    """Raise ``ValueError`` unless ``n_steps`` is an int in [1, 2**31) and ``record_every`` an int >= 0
    dividing it (numpy integers are accepted; floats are not)."""
    def is_int(x: object) -> TypeGuard[numbers.Integral]:
        return isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_))

    if not is_int(n_steps) or not 1 <= int(n_steps) < 2**31:
        raise ValueError(f"n_steps must be an int in [1, 2**31) (the rollout counts steps in int32), got {n_steps!r}")
    if not is_int(record_every) or record_every < 0:
        raise ValueError(f"record_every must be an int >= 0 (0: no trajectory), got {record_every!r}")
    if record_every and n_steps % record_every:
        raise ValueError(f"n_steps={n_steps} is not a multiple of record_every={record_every}")


def _h_mix_np(h: np.ndarray, vals: dict[str, np.ndarray]) -> np.ndarray:
    """``fundamental.h_mix`` at time gap ``h`` (s) on a dict of float64 arrays (the fields of ``FLOAT_FIELDS``)."""
    return cast(np.ndarray, fundamental.h_mix_of(h, vals["alpha"], vals["tau_acc"], vals["tau_m"], vals["h_m"]))


def _equilibrium_np(vals: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    hm = _h_mix_np(vals["h_bar"], vals)
    v_bar = vals["l"] / (1.0 / vals["q_in"] - hm)
    return 1.0 / (vals["l"] + hm * v_bar), v_bar


def equilibrium(p: TrafficParams) -> tuple[jax.Array, jax.Array]:
    """Uniform equilibrium (rho_bar in veh/m, v_bar in m/s) at inflow q_in and time gap h_bar.

    v_bar = l / (1/q_in - h_mix(h_bar)),  rho_bar = 1 / (l + h_mix(h_bar) v_bar).
    """
    hm = fundamental.h_mix(p.h_bar, p)
    v_bar = p.l / (1.0 / p.q_in - hm)
    rho_bar = 1.0 / (p.l + hm * v_bar)
    return jnp.asarray(rho_bar), jnp.asarray(v_bar)


def cfl_number(p: TrafficParams) -> float:
    """CFL number max|lambda| dt_s/dx at the equilibrium (h = h_bar; dt_s = ``solver_dt``), for
    concrete parameters."""
    rho_bar, v_bar = equilibrium(p)
    lam1, lam2 = fundamental.characteristic_speeds(rho_bar, v_bar, p.h_bar, p)
    return float(jnp.max(jnp.maximum(jnp.abs(lam1), jnp.abs(lam2)) * p.solver_dt / p.dx))


def cfl_bound(p: TrafficParams) -> float:
    """The CFL number the construction check bounds (``check_params``): max|lambda| dt_s/dx at the
    equilibrium density over the whole actuator range h in [h_min, h_max]. |lambda2| = |v - 1/(rho
    h_mix(h))| is largest at h = h_min (about 14 m/s at the defaults against 3.6 at h_bar), which a
    controller reaches whenever it saturates, so the equilibrium CFL (``cfl_number``) is not a
    sufficient guard: 1601 points at dt = 0.1 s have an equilibrium CFL of 0.58 and blow up."""
    vals = {k: np.asarray(getattr(p, k), np.float64) for k in FLOAT_FIELDS}
    return float(_cfl_bound_np(vals, p.n_points, p.substeps))


def _cfl_bound_np(vals: dict[str, np.ndarray], n_points: int, substeps: int) -> float:
    """``cfl_bound`` on a dict of float64 arrays (possibly batched: the largest over the batch)."""
    rho_bar, v_bar = _equilibrium_np(vals)
    hm = _h_mix_np(vals["h_min"], vals)
    # a noisy plant alpha reaches 1, where h_mix(h_min) = h_min is smallest (h_min < h_m)
    hm = np.where(vals["alpha_noise"] > 0, np.minimum(hm, vals["h_min"]), hm)
    lam2 = v_bar - 1.0 / (rho_bar * hm)
    dx = vals["L"] / (n_points - 1)
    return float(np.max(np.maximum(np.abs(v_bar), np.abs(lam2)) * vals["dt"] / substeps / dx))


def steps_for(p: TrafficParams, seconds: float) -> int:
    """Number of time steps covering ``seconds`` (concrete dt)."""
    return int(math.ceil(round(seconds / float(p.dt), 6)))
