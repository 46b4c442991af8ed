"""Fundamental diagram of the mixed ACC/manual ARZ model (docs/model.md section 2).

Every function is pure and elementwise, so it broadcasts over grids and ``vmap``s over
parameters. Units: density ``rho`` in veh/m, speed in m/s, time gaps in s.
"""

from __future__ import annotations

from typing import Protocol

import jax.numpy as jnp
import numpy as np

Array = jnp.ndarray
# a value these functions take and return: an array (JAX or numpy) or, where every input is one, a Python float
Num = Array | np.ndarray | float


class MixtureConstants(Protocol):
    """What these functions read from their parameter argument (``model.params.TrafficParams`` has it;
    this module imports nothing from ``params``, so the imports flow one way: params -> fundamental).

    Attributes: alpha (ACC penetration rate, dimensionless), tau_acc and tau_m (relaxation times, s),
    h_m (manual time gap, s), l (effective vehicle length, m). Scalars or arrays that broadcast.
    """

    # read-only properties: a class whose fields are floats (or arrays) alone conforms too
    @property
    def alpha(self) -> Num: ...
    @property
    def tau_acc(self) -> Num: ...
    @property
    def tau_m(self) -> Num: ...
    @property
    def h_m(self) -> Num: ...
    @property
    def l(self) -> Num: ...  # noqa: E743 (the vehicle length's name in the paper and TrafficParams)


def tau_mix(p: MixtureConstants, alpha: Num | None = None) -> Num:
    """Mixed relaxation time tau_mix = 1 / (alpha/tau_acc + (1-alpha)/tau_m), in s."""
    a = p.alpha if alpha is None else alpha
    return 1.0 / (a / p.tau_acc + (1.0 - a) / p.tau_m)


def mix_coefficients(p: MixtureConstants, alpha: Num | None = None) -> tuple[Num, Num]:
    """Coefficients (c, b) of h_mix(h) = c h / (alpha + b h): c = alpha + (1 - alpha) tau_acc/tau_m
    (dimensionless), b = (1 - alpha) tau_acc / (tau_m h_m) (1/s). h_mix saturates at c / b (s)."""
    a = p.alpha if alpha is None else alpha
    return mix_coefficients_of(a, p.tau_acc, p.tau_m, p.h_m)


def mix_coefficients_of(alpha: Num, tau_acc: Num, tau_m: Num,
                        h_m: Num) -> tuple[Num, Num]:
    """``mix_coefficients`` from the constants themselves (numpy or JAX arrays, or floats, broadcast).

    Args:
        alpha: ACC penetration rate in [0, 1]. tau_acc, tau_m: relaxation times, s. h_m: manual time gap, s.
    Returns:
        (c, b): c dimensionless, b in 1/s, in the precision of the inputs.
    """
    ratio = tau_acc / tau_m
    c = alpha + (1.0 - alpha) * ratio
    b = (1.0 - alpha) * ratio / h_m
    return c, b


def h_mix(h: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """Mixed time gap h_mix(h) = c h / (alpha + b h) in s, for an ACC time gap ``h`` in s."""
    a = p.alpha if alpha is None else alpha
    return h_mix_of(h, a, p.tau_acc, p.tau_m, p.h_m)


def h_mix_of(h: Num, alpha: Num, tau_acc: Num, tau_m: Num,
             h_m: Num) -> Num:
    """``h_mix`` from the constants themselves (numpy or JAX arrays, or floats, broadcast).

    Args:
        h: ACC time gap, s. alpha: penetration rate in [0, 1]. tau_acc, tau_m: relaxation times, s.
        h_m: manual time gap, s.
    Returns:
        The mixed time gap c h / (alpha + b h), s, shape of the broadcast inputs.
    """
    c, b = mix_coefficients_of(alpha, tau_acc, tau_m, h_m)
    return c * h / (alpha + b * h)


def h_mix_prime(h: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """Derivative dh_mix/dh = c alpha / (alpha + b h)^2 (dimensionless)."""
    a = p.alpha if alpha is None else alpha
    c, b = mix_coefficients(p, a)
    return c * a / (a + b * h) ** 2


def h_mix_inv(hm: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """Inverse of ``h_mix``: the ACC time gap (s) giving mixed gap ``hm`` (s); needs hm < c/b."""
    a = p.alpha if alpha is None else alpha
    c, b = mix_coefficients(p, a)
    return a * hm / (c - b * hm)


def V(rho: Num, h: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """Equilibrium speed V(rho, h) = (1/rho - l) / h_mix(h), in m/s."""
    return (1.0 / rho - p.l) / h_mix(h, p, alpha)


def dV_drho(rho: Num, h: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """dV/drho = -1 / (rho^2 h_mix(h)), in m^2/(s veh)."""
    return -1.0 / (rho**2 * h_mix(h, p, alpha))


def dV_dh(rho: Num, h: Num, p: MixtureConstants, alpha: Num | None = None) -> Num:
    """dV/dh = -(1/rho - l) h_mix'(h) / h_mix(h)^2, in m/s^2."""
    hm = h_mix(h, p, alpha)
    return -(1.0 / rho - p.l) * h_mix_prime(h, p, alpha) / hm**2


def characteristic_speeds(
    rho: Num, v: Num, h: Num, p: MixtureConstants, alpha: Num | None = None
) -> tuple[Num, Num]:
    """Characteristic speeds (lambda1, lambda2) = (v, v - 1/(rho h_mix)), in m/s."""
    return v, v - 1.0 / (rho * h_mix(h, p, alpha))


def in_physical_region(rho: Array | np.ndarray, v: Array | np.ndarray, l: Num) -> Array | np.ndarray:
    """Elementwise: the node is finite and in the physical region 0 < rho < 1/l, 0 <= v < inf.

    A NaN fails every comparison, an infinite rho fails rho < 1/l. Only comparisons, so it works
    on numpy arrays (in their precision) as well as on JAX arrays.
    """
    return (rho > 0) & (rho < 1.0 / l) & (v >= 0) & (v < float("inf"))
