"""Rollout outcomes (sim.outcome) and the grouped rollout options (sim.options)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.sim.outcome import DivergedError, Divergence, check_outcome

P = jt.TrafficParams(n_points=21)


def test_divergence_codes_and_messages():
    assert [int(d) for d in Divergence] == [0, 1, 2, 3, 4]
    assert Divergence(1).message == "state left the physical region"
    assert Divergence.CONTROL.message == "controller output not finite"
    assert len({d.message for d in Divergence}) == len(Divergence)


def _state_divergence(q_in):
    """A traced inflow far above capacity: the inlet density leaves the physical region at step 1."""
    rho, v = jt.paper_initial_condition(P)
    return jax.jit(lambda q: jt.simulate(P.replace(q_in=q), jt.lyapunov(1.0), n_steps=5, rho0=rho, v0=v))(q_in)


def test_check_outcome_raises_on_a_diverged_rollout_only():
    sick = _state_divergence(jnp.float32(2.0))
    assert int(sick.metrics["diverged_reason"]) == Divergence.STATE
    with pytest.raises(DivergedError, match="STATE: state left the physical region") as err:
        check_outcome(sick)
    assert int(err.value.reasons) == 1
    assert check_outcome(sick, throw=False) == [Divergence.STATE]
    healthy = jt.simulate(P, jt.lyapunov(1.0), n_steps=5)
    assert check_outcome(healthy) == [Divergence.NONE]
    assert check_outcome(healthy.final) == [Divergence.NONE]


def test_check_outcome_names_the_environments_of_a_batch():
    ctrl = jt.Controller(settings=jnp.asarray([0.0, 1e9, 0.0]),  # environment 1: NaN from t = 0
                         act_fn=lambda s, c, obs, nom, k: (jnp.where(s > 1, jnp.nan, nom.h_bar) + 0 * obs.rho, c))
    res = jt.simulate_batch(P, ctrl, n_steps=5, batch_controller=True)
    with pytest.raises(DivergedError, match=r"CONTROL: controller output not finite \(environment\(s\) \[1\]\)"):
        jt.check_outcome(res)
    assert check_outcome(res.metrics, throw=False) == [Divergence.NONE, Divergence.CONTROL, Divergence.NONE]


def test_check_outcome_is_host_side():
    with pytest.raises(TypeError, match="cannot run under jit"):
        jax.jit(lambda r: check_outcome({"diverged_reason": r}))(jnp.int32(0))
    with pytest.raises(TypeError, match="needs a SimResult"):
        check_outcome(42)


def test_options_are_checked():
    with pytest.raises(ValueError, match="record_every must be an int >= 0"):
        jt.Record(every=-1)
    with pytest.raises(ValueError, match="chunk_size must be None or an int"):
        jt.Memory(chunk_size=1.5)
    with pytest.raises(ValueError, match="remat needs record_every > 0"):
        jt.simulate(P, n_steps=5, memory=jt.Memory(remat=True))
    with pytest.raises(TypeError, match="record must be a Record"):
        jt.simulate(P, n_steps=5, record=5)
    assert jt.Record(every=np.int64(5)).every == 5 and type(jt.Record(every=np.int64(5)).every) is int


def test_record_option_records_the_trajectory():
    res = jt.simulate(P, n_steps=10, record=jt.Record(every=5))
    assert np.asarray(res.trajectory.t).tolist() == pytest.approx([0.0, 0.5])
    assert jt.simulate(P, n_steps=10).trajectory is None
