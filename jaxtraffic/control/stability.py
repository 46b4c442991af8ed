"""Stability certificate of the three-gain law with input delay (docs/model.md section 16).

The linearised plant (``model.linear``) on the whole line, one Fourier mode exp(i k x) at a time:

    d/dt [rho^, v^] = A(k) [rho^, v^] + [0, V_h / tau] U(t - D),
    A(k) = [[-i k v_bar,   -i k rho_bar             ],
            [V_rho / tau,  -i k lambda2 - 1 / tau   ]]

(continuous in x; ``symbol="upwind"`` replaces i k by the symbols of the first-order upwind
differences on a grid of spacing dx, the semi-discrete scheme of ``solver``, to explain what a
grid's numerical diffusion does). The three-gain law acts every control period T with the input
held in between (zero-order hold), and reaches the plant d = D / T periods later:

    U_n = -eta1 U_{n-1} + F(k) h_bar (eta3 rho^_n / rho_bar - eta2 v^_n / v_bar),

F(k) = exp(-(k sigma)^2 / 2) for a Gaussian spatial filter of width sigma (m) on the observed
fields (1 without one). Exactly discretised over one period (Phi = e^{A T}, Gamma = int_0^T e^{A s}
ds B), the mode and its d pending inputs form a linear recurrence of dimension 2 + max(d, 1); its
spectral radius rho(k) gives the growth rate sigma(k) = log rho(k) / T (1/s). The law is
*certified* when max_k sigma(k) <= 0 over wavelengths from 2 L down to
``MIN_WAVELENGTH`` (high wavenumbers included: the delayed pointwise law destabilises them), and *marginal*
when it grows slower than ``GROWTH_TOL`` (``verdict``); ``Certificate.stable`` and the trainers' checks accept both.

What it does not see: the road's ends (the inflow and outflow boundaries; a finite road flushes
slowly growing waves out in about L / v_bar = 320 s), saturation of the actuator, the alpha the
plant really has (the certificate takes the plant's alpha; it need not be the nominal one) and
the gains' own dynamics (a state-dependent policy is certified at the gains it settles to at the
equilibrium, ``gain_policy.equilibrium_gains``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, cast

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from jaxtraffic.control.gain_law import DelaySchedule, schedule_gains
from jaxtraffic.model.linear import LinearModel, linearize
from jaxtraffic.model.params import TrafficParams

Array = jax.Array

GROWTH_TOL = 1e-3  # 1/s: growth rates below it (an e-fold in over 1000 s) pass the training's certificate check


def verdict(max_growth: float) -> str:
    """The certificate's word for a largest growth rate (1/s): "certified" (every mode decays or is neutral,
    <= 0), "marginal" (grows, but slower than ``GROWTH_TOL``: an e-fold in over 1000 s, which the training's check
    lets pass) or "not certified"."""
    return "certified" if max_growth <= 0.0 else "marginal" if max_growth <= GROWTH_TOL else "not certified"
MIN_WAVELENGTH = 0.25  # m: the shortest wavelength checked (every grid this project runs is coarser)
N_WAVENUMBERS = 192  # log-spaced wavenumbers of ``wavenumbers``
SYMBOLS = ("pde", "upwind")


def wavenumbers(L: float = 1000.0, min_wavelength: float = MIN_WAVELENGTH, n: int = N_WAVENUMBERS) -> np.ndarray:
    """Log-spaced wavenumbers k = 2 pi / wavelength (rad/m), wavelengths from 2 L down to ``min_wavelength``."""
    return 2.0 * np.pi / np.geomspace(2.0 * L, min_wavelength, n)


def _plant_matrices(k: Array, lm: LinearModel, T: Array | float, symbol: str, dx: Array | float
                    ) -> tuple[Array, Array]:
    """(Phi, Gamma): the mode's exact one-period transition and held-input response, shapes (2, 2), (2,)."""
    ik = 1j * k
    if symbol == "pde":
        back = fwd = ik
    else:  # backward / forward differences of the upwind scheme (v_bar > 0 > lambda2)
        back = (1.0 - jnp.exp(-ik * dx)) / dx
        fwd = (jnp.exp(ik * dx) - 1.0) / dx
    A = jnp.array([[-lm.v_bar * back, -lm.rho_bar * back],
                   [lm.V_rho / lm.tau + 0j, -lm.lam2 * fwd - 1.0 / lm.tau]])
    M = jnp.zeros((3, 3), jnp.complex64 if jnp.result_type(float) == jnp.float32 else jnp.complex128)
    M = M.at[:2, :2].set(A * T).at[1, 2].set(lm.V_h / lm.tau * T)
    E = jsl.expm(M)
    return E[:2, :2], E[:2, 2]


def closed_loop_matrix(k: Array, gains: Array, lm: LinearModel, delay_periods: Array, max_periods: int,
                       T: Array | float, sigma: Array | float = 0.0, symbol: str = "pde",
                       dx: Array | float = 5.0) -> Array:
    """The recurrence of mode k under the delayed three-gain law, shape (2 + m, 2 + m), m = max(1,
    ``max_periods``): state (rho^_n, v^_n, U_{n-1}, ..., U_{n-m}). ``delay_periods`` d <= m may be traced."""
    m = max(1, int(max_periods))
    Phi, Gam = _plant_matrices(k, lm, T, symbol, dx)
    F = jnp.exp(-0.5 * (k * sigma) ** 2)
    K = lm.h_bar * F * jnp.stack([gains[2] / lm.rho_bar, -gains[1] / lm.v_bar]).astype(Phi.dtype)
    u_row = jnp.zeros((2 + m,), Phi.dtype).at[:2].set(K).at[2].set(-gains[0])  # U_n from the state
    now = delay_periods == 0
    pending = jax.nn.one_hot(2 + delay_periods - 1, 2 + m, dtype=Phi.dtype) * jnp.where(now, 0.0, 1.0)
    applied = jnp.where(now, u_row, pending)  # the input the plant receives this period, as a row
    Z = jnp.zeros((2 + m, 2 + m), Phi.dtype)
    Z = Z.at[:2, :2].set(Phi).at[:2, :].add(jnp.outer(Gam, applied))
    Z = Z.at[2, :].set(u_row)
    shift = jnp.eye(m - 1, m, dtype=Phi.dtype)  # U_{n-j} <- U_{n-j+1}
    return Z.at[3:, 2:].set(shift)


def growth_rates(gains: Array, p: TrafficParams, delay: float, k: Array | None = None, sigma: Array | float = 0.0,
                 symbol: str = "pde", dx: float | None = None) -> Array:
    """Growth rate sigma(k) (1/s) of every wavenumber ``k`` (rad/m; default ``wavenumbers(L)``) under the
    three-gain law ``gains`` (eta1, eta2, eta3), applied every ``p.dt`` with input delay ``delay``
    (s, a multiple of dt) to the linearised plant of ``p`` (its alpha), Gaussian filter ``sigma`` (m).
    ``symbol``: "pde" (continuous in x) or "upwind" (the upwind scheme on spacing ``dx``, default p.dx)."""
    if symbol not in SYMBOLS:
        raise ValueError(f"symbol must be one of {SYMBOLS}, got {symbol!r}")
    d = int(round(float(delay) / float(p.dt)))
    if d < 0 or abs(d * float(p.dt) - float(delay)) > 1e-6:
        raise ValueError(f"delay must be a non-negative multiple of dt = {float(p.dt)} s, got {delay}")
    k = jnp.asarray(wavenumbers(float(p.L)) if k is None else k)
    return model_growth_rates(jnp.asarray(gains), linearize(p), d, k, sigma, symbol, p.dx if dx is None else dx)


def model_growth_rates(gains: Array, lm: LinearModel, delay_periods: int, k: Array, sigma: Array | float = 0.0,
                       symbol: str = "pde", dx: Array | float = 5.0, differentiable: bool = False) -> Array:
    """``growth_rates`` on a ``LinearModel`` (its dt the control period) and a static delay in periods:
    traceable; ``differentiable`` (static): also differentiable in the gains (``dominant_eigenvalue``, a
    training penalty, ``learn.gradient.objective``), else the cheaper spectral radius alone."""

    def one(kk):
        Z = closed_loop_matrix(kk, gains, lm, jnp.asarray(delay_periods), delay_periods, lm.dt, sigma, symbol, dx)
        radius = jnp.abs(dominant_eigenvalue(Z)) if differentiable else _spectral_radius(Z)
        return jnp.log(radius) / lm.dt

    return jax.vmap(one)(k)


def _spectral_radius(Z: Array) -> Array:
    """max |eig(Z)| (batched over leading axes), by numpy on the host (``_dominant_eigenpair`` says why)."""
    shape = jax.ShapeDtypeStruct(Z.shape[:-2], jnp.finfo(Z.dtype).dtype)

    def radius(z):
        z = np.asarray(z)
        finite = np.all(np.isfinite(z), axis=(-2, -1))  # a non-finite matrix (gains gone inf): radius inf
        r = np.max(np.abs(np.linalg.eigvals(np.where(finite[..., None, None], z, 0))), axis=-1)
        return np.where(finite, r, np.inf).astype(shape.dtype)

    return jax.pure_callback(radius, shape, Z, vmap_method="broadcast_all")


def dominant_eigenvalue(Z: Array) -> Array:
    """The eigenvalue of largest modulus of the square complex matrix ``Z``, differentiable in Z by first-order
    perturbation theory, lambda' = u^H Z' v / (u^H v) with v, u its right and left eigenvectors (JAX's own
    derivative of ``eig`` is far slower here: minutes for a 42 x 42 batch of 96 that this does in 0.3 s)."""
    Zs = jax.lax.stop_gradient(Z)
    lam, v, u = _dominant_eigenpair(Zs)
    return lam + (jnp.conj(u) @ ((Z - Zs) @ v)) / (jnp.conj(u) @ v)


def _dominant_eigenpair(Z: Array) -> tuple[Array, Array, Array]:
    """(lambda, right eigenvector, left eigenvector) of the eigenvalue of largest modulus of ``Z`` (batched over
    leading axes), by numpy's LAPACK on the host (``jax.pure_callback``): XLA's CPU ``eig`` deadlocks now and
    then inside a jitted, vmapped program on a 2-device CPU setup (docs/model.md section 16). Call it from a
    program on one device."""
    vec = jax.ShapeDtypeStruct(Z.shape[:-1], Z.dtype)
    shapes = (jax.ShapeDtypeStruct(Z.shape[:-2], Z.dtype), vec, vec)

    def host(z):
        z = np.asarray(z)
        finite = np.all(np.isfinite(z), axis=(-2, -1))
        z = np.where(finite[..., None, None], z, 0)
        w, V = np.linalg.eig(z)
        wl, U = np.linalg.eig(np.conj(np.swapaxes(z, -1, -2)))  # left: right ones of Z^H, eigenvalues conjugated
        i = np.argmax(np.abs(w), axis=-1)[..., None]
        lam = np.take_along_axis(w, i, -1)
        j = np.argmin(np.abs(wl - np.conj(lam)), axis=-1)[..., None]
        v = np.take_along_axis(V, i[..., None, :], -1)[..., 0]
        u = np.take_along_axis(U, j[..., None, :], -1)[..., 0]
        lam = np.where(finite, lam[..., 0], np.inf)  # a non-finite matrix (gains gone inf): growth inf
        return lam.astype(z.dtype), v.astype(z.dtype), u.astype(z.dtype)

    return jax.pure_callback(host, shapes, Z, vmap_method="broadcast_all")


@dataclasses.dataclass(frozen=True)
class Certificate:
    """The verdict for one law and plant: the largest growth rate (1/s) over the wavenumbers checked,
    the wavelength (m) where it occurs, whether it is <= ``GROWTH_TOL``, and the settings used."""

    max_growth: float
    worst_wavelength: float
    stable: bool
    gains: tuple[float, float, float]
    delay: float
    alpha: float
    sigma: float
    symbol: str

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def certify(gains: Array, p: TrafficParams, delay: float, sigma: float = 0.0, symbol: str = "pde",
            dx: float | None = None) -> Certificate:
    """``Certificate`` of the three-gain law (``growth_rates``) on the wavenumbers of ``wavenumbers(p.L)``
    (with ``symbol="upwind"``: those the grid resolves, wavelengths >= 2 dx)."""
    gains_np = np.asarray(jax.device_get(gains), np.float64)  # on the host: a pure_callback runs on one device
    k = wavenumbers(float(p.L))
    if symbol == "upwind":
        k = k[k * float(p.dx if dx is None else dx) < np.pi]
    g_dev = jnp.asarray(gains_np, jnp.result_type(float))
    s = np.asarray(growth_rates(g_dev, p, delay, jnp.asarray(k), sigma, symbol, dx), np.float64)
    i = int(np.argmax(s))
    g = cast(tuple[float, float, float], tuple(float(x) for x in np.asarray(gains_np)))  # (the three gains)
    return Certificate(max_growth=float(s[i]), worst_wavelength=float(2 * np.pi / k[i]),
                       stable=bool(s[i] <= GROWTH_TOL), gains=g, delay=float(delay), alpha=float(p.alpha),
                       sigma=float(sigma), symbol=symbol)


def certify_controller(controller: Any, nominal: TrafficParams, delay: float, sigma: float) -> Certificate:
    """``certify`` of a gain controller (constant gains, a delay schedule at its told delay, a policy) at the
    gains it settles to while the plant sits at ``nominal``'s equilibrium (``gain_policy.equilibrium_gains``;
    ``nominal`` on the controller's own grid, its dt the control period), with its filter width ``sigma`` (m)."""
    from jaxtraffic.control.gain_policy import equilibrium_gains

    settings = controller.settings
    if isinstance(settings, DelaySchedule):  # the gains it applies at its told delay
        gains = schedule_gains(settings)
    else:
        gains = settings if getattr(settings, "shape", None) == (3,) else equilibrium_gains(controller, nominal)
    return certify(gains, nominal, delay, sigma)


def stable_region(p: TrafficParams, delay: float, eta1: float, eta2: np.ndarray, eta3: np.ndarray,
                  sigma: float = 0.0, symbol: str = "pde", k: np.ndarray | None = None) -> np.ndarray:
    """max_k sigma(k) (1/s) on the grid ``eta2`` x ``eta3`` at fixed ``eta1``, shape (len(eta2), len(eta3))."""
    k_dev = jnp.asarray(wavenumbers(float(p.L), n=96) if k is None else k)
    e2, e3 = np.meshgrid(np.asarray(eta2, float), np.asarray(eta3, float), indexing="ij")
    g = jnp.asarray(np.stack([np.full(e2.size, eta1), e2.ravel(), e3.ravel()], axis=1))
    fn = jax.jit(jax.vmap(lambda gg: jnp.max(growth_rates(gg, p, delay, k_dev, sigma, symbol))))
    return np.asarray(jax.lax.map(fn, g.reshape(len(eta2), len(eta3), 3)))
