"""Parameters, fundamental diagram oracles (docs/model.md section 2) and parameter validation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic
from jaxtraffic import TrafficParams, cfl_number, equilibrium, stack_params, steps_for
from jaxtraffic.model import fundamental as fd

# docs/model.md section 2.4 table: (value, decimals shown)
ORACLES = {
    "tau_mix": (11.214953, 6),
    "h_mix(h_bar)": (1.389610, 6),
    "v_bar": (3.104839, 6),
    "rho_bar": (0.10735931, 8),
    "dV/drho": (-62.43492, 5),
    "dV/dh": (-1.612903, 6),
    "lambda1": (3.10484, 5),
    "lambda2": (-3.59813, 5),
}


def _derived(p: TrafficParams) -> dict[str, float]:
    rho_bar, v_bar = equilibrium(p)
    lam1, lam2 = fd.characteristic_speeds(rho_bar, v_bar, p.h_bar, p)
    return {
        "tau_mix": fd.tau_mix(p),
        "h_mix(h_bar)": fd.h_mix(p.h_bar, p),
        "v_bar": v_bar,
        "rho_bar": rho_bar,
        "dV/drho": fd.dV_drho(rho_bar, p.h_bar, p),
        "dV/dh": fd.dV_dh(rho_bar, p.h_bar, p),
        "lambda1": lam1,
        "lambda2": lam2,
    }


def test_oracle_values_to_the_digits_shown(x64):
    got = _derived(TrafficParams())
    for name, (value, decimals) in ORACLES.items():
        x = float(got[name])
        assert round(x, decimals) == pytest.approx(value, abs=1e-12), f"{name}: {x!r} vs {value}"


def test_public_equilibrium_float32_default():
    rho_bar, v_bar = jaxtraffic.equilibrium(jaxtraffic.TrafficParams())
    assert float(rho_bar) == pytest.approx(0.10735931, rel=2e-7)
    assert float(v_bar) == pytest.approx(3.104839, rel=2e-7)


def test_equilibrium_identities(x64):
    """V(rho_bar, h_bar) = v_bar, rho_bar v_bar = q_in, lambda2 = -l / h_mix(h_bar)."""
    for alpha, q_in in [(0.15, 1 / 3), (0.5, 0.3), (1.0, 0.2), (0.0, 0.25)]:
        p = TrafficParams(alpha=alpha, q_in=q_in)
        rho_bar, v_bar = equilibrium(p)
        np.testing.assert_allclose(fd.V(rho_bar, p.h_bar, p), v_bar, rtol=1e-13)
        np.testing.assert_allclose(rho_bar * v_bar, q_in, rtol=1e-13)
        _, lam2 = fd.characteristic_speeds(rho_bar, v_bar, p.h_bar, p)
        np.testing.assert_allclose(lam2, -p.l / fd.h_mix(p.h_bar, p), rtol=1e-13)


def test_derivatives_match_autodiff(x64):
    p = TrafficParams()
    rho = jnp.linspace(0.03, 0.19, 7)
    h = jnp.linspace(0.5, 3.0, 7)
    dvdrho = jax.vmap(jax.grad(lambda r, hh: fd.V(r, hh, p)))(rho, h)
    dvdh = jax.vmap(jax.grad(lambda r, hh: fd.V(r, hh, p), argnums=1))(rho, h)
    dhm = jax.vmap(jax.grad(lambda hh: fd.h_mix(hh, p)))(h)
    np.testing.assert_allclose(fd.dV_drho(rho, h, p), dvdrho, rtol=1e-12)
    np.testing.assert_allclose(fd.dV_dh(rho, h, p), dvdh, rtol=1e-12)
    np.testing.assert_allclose(fd.h_mix_prime(h, p), dhm, rtol=1e-12)


@pytest.mark.parametrize("alpha", [0.05, 0.15, 0.6, 1.0])
def test_h_mix_inverse(x64, alpha):
    p = TrafficParams(alpha=alpha)
    h = jnp.linspace(0.2, 5.0, 25)
    np.testing.assert_allclose(fd.h_mix_inv(fd.h_mix(h, p), p), h, rtol=1e-12)
    c = alpha + (1 - alpha) * p.tau_acc / p.tau_m
    b = (1 - alpha) * p.tau_acc / p.tau_m / p.h_m
    H = jnp.linspace(0.1, 0.99 * c / b, 25) if b > 0 else jnp.linspace(0.1, 5.0, 25)
    np.testing.assert_allclose(fd.h_mix(fd.h_mix_inv(H, p), p), H, rtol=1e-10)


def test_tau_mix_limits():
    assert float(fd.tau_mix(TrafficParams(alpha=0.0))) == pytest.approx(60.0)
    assert float(fd.tau_mix(TrafficParams(alpha=1.0))) == pytest.approx(2.0)


def test_grid_and_cfl_number():
    p = TrafficParams()
    assert p.n_points == 201 and float(p.dx) == 5.0 and float(p.x()[-1]) == 1000.0
    # max |lambda| = |lambda2| = 3.598 m/s, dt/dx = 0.02
    assert cfl_number(p) == pytest.approx(3.59813 * 0.1 / 5.0, rel=1e-5)
    assert steps_for(p, 300.0) == 3000 and steps_for(p, 4.0) == 40


# ----------------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"L": 0.0}, "L must be > 0"),
        ({"L": -1000.0}, "L must be > 0"),
        ({"l": 0.0}, "l must be > 0"),
        ({"l": -5.0}, "l must be > 0"),
        ({"dt": 0.0}, "dt must be > 0"),
        ({"tau_m": -1.0}, "tau_m must be > 0"),
        ({"tau_acc": 0.0}, "tau_acc must be > 0"),
        ({"h_m": 0.0}, "h_m must be > 0"),
        ({"q_in": 0.0}, "q_in must be > 0"),
        ({"alpha": -0.01}, r"alpha must lie in \[0, 1\]"),
        ({"alpha": 1.01}, r"alpha must lie in \[0, 1\]"),
        ({"alpha_noise": -0.1}, "alpha_noise must be >= 0"),
        # 1/q_in = 1 s < h_mix(h_bar) = 1.39 s: no equilibrium
        ({"q_in": 1.0}, "has no equilibrium"),
        ({"q_in": 1.0 / 1.389}, "has no equilibrium"),
        ({"delay": 0.15}, "multiple of dt"),
        ({"delay": -0.1}, "non-negative multiple of dt"),
        ({"delay": 10.1}, "above the buffer capacity"),
        ({"delay": 2.0, "max_delay_steps": 10}, "above the buffer capacity"),
        # at h = h_min |lambda2| = 14.05 m/s: 14.05 dt / dx > 1 (the equilibrium's 3.6 m/s is not the bound)
        ({"dt": 2.0}, "CFL violated"),
        ({"dt": 0.4}, "CFL violated"),  # 1.12; at h_bar only 0.29
        ({"n_points": 1601}, "CFL violated"),  # dx = 0.625 m: 2.25 (0.58 at h_bar)
        ({"n_points": 1601, "substeps": 2}, "CFL violated"),  # 1.12
        ({"substeps": 0}, "substeps must be an int >= 1"),
        ({"n_points": 2}, "n_points must be an int >= 3"),
        ({"max_delay_steps": -1}, "max_delay_steps"),
        ({"scheme": "weno"}, "scheme must be one of"),
        ({"h_bar": 4.0}, "outside actuator bounds"),
        ({"h_min": 2.0, "h_max": 1.0}, "h_max > h_min"),
    ],
)
def test_invalid_parameters_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrafficParams(**kwargs)


def test_invalid_replace_raises():
    """``replace`` re-validates (dataclass __post_init__)."""
    with pytest.raises(ValueError, match="multiple of dt"):
        TrafficParams().replace(delay=0.25)


def test_valid_edge_cases():
    TrafficParams(delay=0.0)
    TrafficParams(delay=10.0)  # exactly the capacity: 100 steps of 0.1 s
    TrafficParams(alpha=0.0)
    TrafficParams(alpha=1.0)
    TrafficParams(dt=0.35)  # CFL bound 0.98 <= 1
    TrafficParams(n_points=1601, substeps=4)  # 0.56
    TrafficParams(dt=1.3, substeps=4)  # 0.91
    assert TrafficParams(delay=0.3).delay_steps == 3


def test_stack_params_validates_every_environment():
    with pytest.raises(ValueError, match="multiple of dt"):
        stack_params(delay=[0.0, 0.4, 0.45])
    with pytest.raises(ValueError, match=r"alpha must lie in \[0, 1\]"):
        stack_params(alpha=[0.1, 1.5])
    with pytest.raises(ValueError, match="different lengths"):
        stack_params(alpha=[0.1, 0.2], delay=[0.0])
    p = stack_params(alpha=[0.1, 0.2, 0.3], n_points=21)
    assert p.n_points == 21
    assert np.asarray(p.alpha).shape == (3,) and np.asarray(p.L).shape == (3,)
    np.testing.assert_allclose(np.asarray(p.alpha), [0.1, 0.2, 0.3], rtol=1e-6)


def test_traced_fields_do_not_recompile():
    """Float fields are traced: a jitted function of the params compiles once for new values."""
    f = jax.jit(lambda p: equilibrium(p)[0])
    f(TrafficParams())
    f(TrafficParams(alpha=0.3, q_in=0.3, delay=1.0))
    assert f._cache_size() == 1
    f(TrafficParams(n_points=21))  # static field: a new program
    assert f._cache_size() == 2


def test_cfl_bound_is_the_speed_characteristic_at_the_smallest_time_gap():
    """The construction check bounds |lambda2| at h = h_min (14.05 m/s at the defaults), not at h_bar
    (3.6 m/s): a saturating controller reaches it (at 1601 points and dt = 0.1 s a local CFL of 1.76 and
    a blow-up, BENCHMARKS.md), so substeps divide the solver step."""
    from jaxtraffic.model import fundamental as fd
    from jaxtraffic.model.params import cfl_bound

    p = TrafficParams()
    rho_bar, v_bar = equilibrium(p)
    lam2 = float(v_bar) - 1.0 / (float(rho_bar) * float(fd.h_mix(p.h_min, p)))
    assert lam2 == pytest.approx(-14.05, abs=0.01)
    assert cfl_bound(p) == pytest.approx(abs(lam2) * 0.1 / 5.0, rel=1e-5)
    q = TrafficParams(n_points=801, substeps=2)
    assert cfl_bound(q) == pytest.approx(abs(lam2) * 0.05 / 1.25, rel=1e-5)
    assert cfl_number(q) == pytest.approx(3.59813 * 0.05 / 1.25, rel=1e-5)
