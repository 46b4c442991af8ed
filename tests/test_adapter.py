"""A controller on another discretisation (control.adapter): identity on its own grid, the hold over its
control period, convergence across grids, clear errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.control.adapter import ControllerGrid, adapt, ratios

P = jt.TrafficParams(n_points=21, delay=2.0, dt=0.5, max_delay_steps=10)
GRID = ControllerGrid.of(P)


@pytest.mark.parametrize("ctrl", [jt.backstepping(2.0), jt.constant_gains(0.3, -0.5, -1.0), jt.lyapunov(1.0),
                                  jt.constant_gains(0.0, -0.5, -1.0, filter_sigma=60.0, dx=50.0)],
                         ids=["backstepping", "gains", "lyapunov", "filtered"])
def test_on_its_own_grid_the_adapted_controller_is_the_controller(ctrl):
    """Same grid and period: its own buffer of sent fields and its own h_prev equal the plant's, so the
    rollout is the same to float32 rounding (XLA may fuse the law differently: 1 ulp here and there;
    backstepping reads the buffer, the gain law h_prev)."""
    a = jt.simulate(P, ctrl, n_steps=300, record=jt.Record(every=10))
    b = jt.simulate(P, adapt(ctrl, GRID, P), n_steps=300, record=jt.Record(every=10))
    np.testing.assert_allclose(a.trajectory.rho, b.trajectory.rho, rtol=1e-5)
    np.testing.assert_allclose(a.trajectory.h, b.trajectory.h, rtol=1e-5)
    assert float(a.metrics["J_comfort"]) == pytest.approx(float(b.metrics["J_comfort"]), rel=1e-4)


def test_the_time_gap_is_held_over_the_control_period():
    fine_t = P.replace(dt=0.25, max_delay_steps=20)
    res = jt.simulate(fine_t, adapt(jt.lyapunov(1.0), GRID, fine_t), n_steps=40, record=jt.Record(every=1))
    h = np.asarray(res.trajectory.h)
    np.testing.assert_array_equal(h[0::2], h[1::2])  # acts at steps 0, 2, 4, ...
    assert np.any(h[2] != h[0])


def test_on_a_refined_plant_the_time_gap_is_the_interpolated_controller_field():
    fine = P.replace(n_points=41)
    res = jt.simulate(fine, adapt(jt.lyapunov(1.0), GRID, fine), n_steps=20, record=jt.Record(every=1))
    h = np.asarray(res.trajectory.h)
    np.testing.assert_allclose(h[:, 1:-1:2], 0.5 * (h[:, 0:-2:2] + h[:, 2::2]), rtol=1e-6)


def test_the_controller_sees_the_restricted_fields_on_its_own_nodes():
    """One act on a plant refined twice: the controller's field is its own law on the full-weighting
    restriction of the plant's fields (and its own nominal), interpolated back."""
    from jaxtraffic.control.base import Observation
    from jaxtraffic.model.spatial import restrict

    fine = P.replace(n_points=41, delay=0.0)
    rho, v = jt.paper_initial_condition(fine)
    obs_f = Observation(rho=rho, v=v, h_prev=jnp.full_like(rho, fine.h_bar), t=jnp.zeros(()), sent=None)
    ctrl = jt.lyapunov(1.0)
    coarse_nom = P.replace(delay=0.0)
    obs_c = Observation(rho=restrict(rho, 2), v=restrict(v, 2), h_prev=jnp.full((21,), P.h_bar), t=jnp.zeros(()),
                        sent=None)
    h_c, _ = ctrl.act((), obs_c, coarse_nom, jax.random.PRNGKey(0))
    wrapped = adapt(ctrl, GRID, fine)
    h_f, _ = wrapped.act(wrapped.init(obs_f, fine), obs_f, fine, jax.random.PRNGKey(0))
    np.testing.assert_allclose(h_f[::2], jt.saturate(h_c, P), rtol=1e-6)
    np.testing.assert_allclose(h_f[1::2], 0.5 * (h_f[:-1:2] + h_f[2::2]), rtol=1e-6)
    assert np.ptp(np.asarray(h_f)) > 0.01


def test_constant_gains_at_zero_delay_converge_across_plant_grids():
    """The same controller (21 points) on plants refined 2, 4, 8 times: the density L2 at 150 s changes
    less at each refinement (the plant's first-order discretisation error shrinks)."""
    gains = jt.constant_gains(0.0, -0.5, -1.5)
    l2 = []
    for n, dt in ((41, 0.5), (81, 0.25), (161, 0.125)):
        q = P.replace(n_points=n, delay=0.0, dt=dt, max_delay_steps=int(10 / dt))
        res = jt.simulate(q, adapt(gains, GRID, q), n_steps=int(150 / dt))
        l2.append(float(res.metrics["final_rho_L2"]))
    d1, d2 = abs(l2[1] - l2[0]), abs(l2[2] - l2[1])
    assert d2 < 0.75 * d1, l2


def test_ratio_errors():
    with pytest.raises(ValueError, match="integer factor"):
        ratios(GRID, P.replace(n_points=31))
    with pytest.raises(ValueError, match="integer factor"):
        ratios(ControllerGrid(41, 0.5, 10), P)  # a plant coarser than the controller
    with pytest.raises(ValueError, match="whole number of plant steps"):
        ratios(GRID, P.replace(dt=0.3, delay=0.0, max_delay_steps=20))
    assert ratios(GRID, P.replace(n_points=81, dt=0.25, max_delay_steps=20)) == (4, 2)


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf, -jnp.inf])
@pytest.mark.parametrize("plant", [P, P.replace(n_points=41, dt=0.25, max_delay_steps=20)], ids=["own", "refined"])
def test_a_non_finite_controller_is_refused_through_the_adapter_as_directly(bad, plant):
    """Issue 50, item 14: a policy whose output is NaN or inf somewhere is not saturated into a healthy-looking
    rollout by the adapter (evaluate.py and the judge adapt every controller): the closed loop refuses its first
    step (reason CONTROL), as ``simulate`` does with the controller acting directly; a finite law is unchanged."""
    ctrl = jt.Controller(settings=jnp.float32(bad),
                         act_fn=lambda s, c, obs, nom, k: (jnp.full_like(obs.rho, nom.h_bar).at[3].set(s), c))
    direct = jt.simulate(P, ctrl, n_steps=6)
    adapted = jt.simulate(plant, adapt(ctrl, GRID, plant), n_steps=12)
    for res in (direct, adapted):
        assert bool(res.metrics["diverged"]) and int(res.metrics["diverged_reason"]) == jt.Divergence.CONTROL
        assert float(res.metrics["diverged_at_s"]) <= 0.5  # its first step (s)
    healthy = jt.simulate(plant, adapt(jt.lyapunov(1.0), GRID, plant), n_steps=12)
    assert not bool(healthy.metrics["diverged"])


def test_a_law_adapted_again_with_new_settings_reuses_its_compiled_rollout():
    """``adapt`` gives every controller of one law on one grid the same functions, so a rollout compiled for it
    runs new settings without tracing or compiling again: a training that validates each checkpoint through the
    adapter used to load one program per validation until the process ran out of memory mappings (and died)."""
    from jaxtraffic.sim.rollout import _simulate_batch_jit

    fine = P.replace(n_points=41)
    plants = jt.stack_params(fine, fine.replace(alpha=0.2))
    first = adapt(jt.lyapunov(0.5), GRID, fine)
    again = adapt(jt.lyapunov(0.7), GRID, fine)
    assert (first.act_fn, first.init_fn) == (again.act_fn, again.init_fn)
    assert adapt(jt.backstepping(2.0), GRID, fine).act_fn is not first.act_fn  # another law: its own functions
    runs = []
    for ctrl in (first, again):
        before = _simulate_batch_jit._cache_size()
        res = jt.simulate_batch(plants, ctrl, n_steps=20, nominal=fine, metrics=("final_rho_L2",))
        runs.append((_simulate_batch_jit._cache_size() - before, np.asarray(res.metrics["final_rho_L2"])))
    assert [n for n, _ in runs] == [1, 0]
    assert not np.array_equal(runs[0][1], runs[1][1])  # the new gain did act
