"""Tests of adaptive backstepping (control.adaptive) on tiny grids."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic import TrafficParams, backstepping, simulate, simulate_batch
from jaxtraffic.control import adaptive_backstepping, tell_delay
from jaxtraffic.control.adapter import ControllerGrid, adapt
from jaxtraffic.control.adaptive import ALPHA_MIN
from jaxtraffic.model.params import equilibrium
from jaxtraffic.sim import Record, paper_initial_condition
from jaxtraffic.sim.rollout import stack_params

N, STEPS = 41, 300  # 30 s at dt = 0.1 s
NOMINAL = TrafficParams(n_points=N, delay=2.0)  # the controller's model: alpha 0.15, told D = 2 s


def _run(plant, ctrl, n_steps=STEPS, record=False):
    rho0, v0 = paper_initial_condition(NOMINAL)
    return simulate(plant, ctrl, n_steps=n_steps, rho0=rho0, v0=v0, nominal=NOMINAL,
                    record=Record(every=1) if record else None)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.6])
def test_estimate_converges_on_the_controllers_grid(alpha):
    """Plant = the controller's model with another alpha: within 0.005 of it after 5 s (50 steps)."""
    plant = NOMINAL.replace(alpha=alpha)
    res = _run(plant, adaptive_backstepping(delay=2.0), n_steps=50)
    assert not bool(res.final.diverged)
    assert abs(float(res.controller_state.alpha_hat) - alpha) < 5e-3


def test_estimate_converges_on_a_finer_muscl_plant():
    """Controller on an 81-point upwind grid (dx 12.5 m), plant MUSCL on 161 points in 2 substeps (through
    the adapter): the one-step model is not the plant's, so the estimate carries the discretisation
    error (measured: 0.343 at 5 s, 0.339 at 30 s for 0.35; on a 41-point grid 0.316 at 30 s, on the
    paper's grid over the reference plant 3e-4): within 0.015 at 5 s and at 30 s."""
    n_ctrl = 2 * N - 1
    plant = TrafficParams(n_points=2 * n_ctrl - 1, scheme="muscl", substeps=2, delay=2.0, alpha=0.35)
    nominal = plant.replace(alpha=0.15)
    ctrl = adapt(adaptive_backstepping(delay=2.0), ControllerGrid(n_points=n_ctrl), plant)
    rho0, v0 = paper_initial_condition(nominal)
    for n in (50, STEPS):
        res = simulate(plant, ctrl, n_steps=n, rho0=rho0, v0=v0, nominal=nominal)
        assert abs(float(res.controller_state.inner.alpha_hat) - 0.35) < 0.015


def test_told_alpha_without_adaptation_equals_backstepping():
    """adapt=False with the nominal's alpha (alpha0 NaN) is backstepping to rounding, on a plant
    whose alpha differs (so the state is far from trivial)."""
    plant = NOMINAL.replace(alpha=0.3)
    a = _run(plant, adaptive_backstepping(delay=2.0, adapt=False, hold_target=False), record=True)
    b = _run(plant, backstepping(delay=2.0), record=True)
    # equal to rounding: the two programs fuse the linearisation differently (1 ulp in h at ~30 % of the
    # entries, measured), and the difference does not grow over 30 s
    np.testing.assert_allclose(np.asarray(a.trajectory.h), np.asarray(b.trajectory.h), rtol=2e-6, atol=0)
    np.testing.assert_allclose(np.asarray(a.final.rho), np.asarray(b.final.rho), rtol=2e-6, atol=0)
    assert float(a.controller_state.alpha_hat) == np.float32(0.15)
    # holding the target (the default) at the nominal alpha: h* = h_bar up to the rounding of h_mix's inverse
    c = _run(plant, adaptive_backstepping(delay=2.0, adapt=False), record=True)
    np.testing.assert_allclose(np.asarray(c.trajectory.h), np.asarray(b.trajectory.h), rtol=1e-5, atol=0)


def test_told_alpha_changes_the_law():
    """Told another alpha (adapt off), the law is backstepping on that model: it differs from the
    nominal one (guards against alpha0 being ignored)."""
    plant = NOMINAL.replace(alpha=0.3)
    a = _run(plant, adaptive_backstepping(delay=2.0, adapt=False, alpha0=0.3), n_steps=60)
    b = _run(plant, backstepping(delay=2.0), n_steps=60)
    assert float(a.controller_state.alpha_hat) == np.float32(0.3)
    assert not np.array_equal(np.asarray(a.final.rho), np.asarray(b.final.rho))


def test_jit_vmap_over_plants_with_different_alphas():
    """One batched call over plants (alpha, delay) with the controller told each delay: every
    estimate near its own plant's alpha."""
    alphas, delays = [0.1, 0.25, 0.5], [1.0, 2.0, 3.0]
    plants = stack_params(*[NOMINAL.replace(alpha=a, delay=d) for a, d in zip(alphas, delays, strict=True)])
    ctrl = tell_delay(adaptive_backstepping(), jnp.asarray(delays))
    rho0, v0 = paper_initial_condition(NOMINAL)
    res = simulate_batch(plants, ctrl, n_steps=100, rho0=jnp.stack([rho0] * 3), v0=jnp.stack([v0] * 3),
                         nominal=NOMINAL, batch_controller=True)
    np.testing.assert_allclose(np.asarray(res.controller_state.alpha_hat), alphas, atol=5e-3)
    assert not np.any(np.asarray(res.final.diverged))


@pytest.mark.parametrize(("alpha", "alpha0"), [(0.0, 0.3), (1.0, 0.6), (0.15, 1.7), (0.15, -0.5)])
def test_projection_keeps_the_estimate_in_unit_interval(alpha, alpha0):
    """Plants at the ends of [0, 1] and initial estimates outside it: every estimate in
    [ALPHA_MIN, 1] (the law needs alpha > 0), the plant never refused a control, and the estimate
    reaches the end the plant is at (or the plant's alpha)."""
    plant = NOMINAL.replace(alpha=alpha)
    ctrl = adaptive_backstepping(delay=2.0, alpha0=min(max(alpha0, 0.0), 1.0))
    # a concrete alpha0 outside [0, 1] is refused (issue 50); a traced one (settings built in a jit) is projected
    ctrl = ctrl.replace(settings=ctrl.settings.replace(alpha0=jnp.float32(alpha0)))
    rho0, v0 = paper_initial_condition(NOMINAL)
    for n in (1, 2, 50):
        res = simulate(plant, ctrl, n_steps=n, rho0=rho0, v0=v0, nominal=NOMINAL)
        a_hat = float(res.controller_state.alpha_hat)
        assert np.float32(ALPHA_MIN) <= a_hat <= 1.0
        assert not bool(res.final.diverged)
    assert abs(a_hat - max(alpha, ALPHA_MIN)) < 5e-3


def test_deterministic():
    plant = NOMINAL.replace(alpha=0.4)
    a, b = (_run(plant, adaptive_backstepping(delay=2.0), n_steps=80) for _ in range(2))
    assert float(a.controller_state.alpha_hat) == float(b.controller_state.alpha_hat)
    np.testing.assert_array_equal(np.asarray(a.final.rho), np.asarray(b.final.rho))


def test_no_information_no_drift():
    """A state that says nothing about alpha: the plant's equilibrium under h = h_m (there h_mix = h_m
    whatever alpha, so every alpha's model has it as a fixed point), before any control reaches it
    (D = 9 s, 8 s simulated). The estimate must not wind up on rounding: it stays where it started.
    (At h_bar = 1.5 s the equilibrium of 0.15 is no equilibrium of 0.3, and the estimate does move.)"""
    plant = NOMINAL.replace(alpha=0.15, delay=9.0, h_bar=1.0)
    rho_bar, v_bar = equilibrium(plant)
    res = simulate(plant, adaptive_backstepping(delay=9.0, alpha0=0.3), n_steps=80,
                   rho0=jnp.full((N,), rho_bar), v0=jnp.full((N,), v_bar), nominal=NOMINAL)
    assert abs(float(res.controller_state.alpha_hat) - 0.3) < 1e-3


@pytest.mark.parametrize("kwargs", [{"forgetting": -0.1}, {"shock_scale": float("nan")}, {"delay": -1.0},
                                    {"k": float("inf")}])
def test_invalid_settings_rejected(kwargs):
    with pytest.raises(ValueError):
        adaptive_backstepping(**kwargs)


def test_state_is_jittable_pytree():
    ctrl = adaptive_backstepping(delay=1.0)
    plant = NOMINAL
    from jaxtraffic.sim import initial_state
    rho0, v0 = paper_initial_condition(NOMINAL)
    obs = initial_state(plant, rho0, v0).observation(plant)
    cs = jax.jit(ctrl.init)(obs, NOMINAL)
    h, cs2 = jax.jit(ctrl.act)(cs, obs, NOMINAL, jax.random.PRNGKey(0))
    assert h.shape == (N,) and bool(cs2.started) and not bool(cs.started)


@pytest.mark.parametrize("alpha_hat", [0.05, 0.15, 0.3, 0.6])
def test_hold_target_model_rests_at_the_nominal_equilibrium(alpha_hat):
    """With hold_target the law's model has the nominal equilibrium (at its time gap h*); without, the
    estimated plant's own at h_bar (which differs unless alpha_hat is the nominal's)."""
    from jaxtraffic.control.adaptive import estimated_model
    held = estimated_model(adaptive_backstepping().settings, NOMINAL, jnp.float32(alpha_hat))
    own = estimated_model(adaptive_backstepping(hold_target=False).settings, NOMINAL, jnp.float32(alpha_hat))
    np.testing.assert_allclose(np.array(equilibrium(held)), np.array(equilibrium(NOMINAL)), rtol=1e-5)
    assert float(own.h_bar) == NOMINAL.h_bar
    assert (abs(float(equilibrium(own)[0]) - float(equilibrium(NOMINAL)[0])) > 1e-5) == (alpha_hat != 0.15)
