"""Gradient-based training (tiny grids): exact gradients, checkpointing, NaN safety, descent,
run directories that load with ``load_policy``."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL

from jaxtraffic import TrafficParams, simulate
from jaxtraffic.cli.train import config_from_args
from jaxtraffic.learn.gradient import objective
from jaxtraffic.runs import load_policy
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.gradient.policy import gradient_setup
from jaxtraffic.runs.gradient.trainer import train_gradient
from jaxtraffic.sim import Record

BASE = TrafficParams(delay=2.0, **SMALL)  # 41 nodes, dt = 0.5 s
CFG = objective.GradientConfig(train_delays=(1.0, 2.0), train_horizon_s=60.0, record_every=10, steps_per_chunk=2)


def _objective(theta, cfg=CFG, base=BASE, remat=True):
    scen = objective.training_scenarios(cfg, base)
    return objective.objective(theta, scen, objective.weights_of(cfg), cfg, base, remat=remat)[0]


def test_gradient_matches_central_differences(x64):
    theta = jnp.asarray([-0.2, -0.3, -0.4])
    g = jax.grad(_objective)(theta)
    eps = 1e-5
    fd = np.array([(_objective(theta.at[i].add(eps)) - _objective(theta.at[i].add(-eps))) / (2 * eps)
                   for i in range(3)])
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-8)
    assert np.all(np.abs(fd) > 1e-4)  # a non-trivial gradient


def test_checkpointed_gradient_equals_plain_one(x64):
    theta = jnp.asarray([-0.1, -0.5, -0.2])
    g_remat = jax.grad(lambda t: _objective(t, remat=True))(theta)
    g_plain = jax.grad(lambda t: _objective(t, remat=False))(theta)
    np.testing.assert_allclose(np.asarray(g_remat), np.asarray(g_plain), rtol=1e-12, atol=1e-14)


def test_no_nan_gradient_when_one_scenario_diverges():
    # these gains drive the large initial wave out of the physical region, not the small one
    cfg = objective.GradientConfig(train_delays=(0.0,), train_amplitudes=(1.0, 80.0), train_horizon_s=100.0,
                                   record_every=10)
    base = TrafficParams(delay=0.0, **SMALL)
    theta = jnp.asarray([0.0, -3.0, 3.0])
    scen = objective.training_scenarios(cfg, base)
    loss_and_grad = jax.value_and_grad(objective.objective, has_aux=True)
    (loss, aux), g = loss_and_grad(theta, scen, objective.weights_of(cfg), cfg, base)
    diverged = np.asarray(aux["diverged"])
    assert diverged.any() and not diverged.all(), diverged
    assert np.isfinite(float(loss)) and np.all(np.isfinite(np.asarray(g))), (loss, g)


def test_a_few_steps_lower_the_objective():
    cfg = objective.GradientConfig(train_delays=(1.0, 2.0), train_horizon_s=60.0, steps_per_chunk=4)
    init, chunk = objective.make_train(cfg, BASE)
    state, m = chunk(init(jax.random.PRNGKey(0)))
    obj = np.asarray(m["objective"])
    assert np.all(np.isfinite(obj)) and obj[-1] < 0.9 * obj[0], obj
    assert int(state.update) == 4


@pytest.mark.slow
def test_network_run_lowers_objective_round_trips_and_resumes_exactly(tmp_path):
    config = TrainConfig.make(run={"algo": "gradient", "out_dir": str(tmp_path / "a"), "eval_horizon_s": 30.0,
                                   "quiet": True},
                              grad={"policy": "network", "train_delays": (2.0,), "train_horizon_s": 30.0,
                                    "steps_per_chunk": 2, "grad_steps": 4},
                              plant={"delay": 2.0, "n_points": SMALL["n_points"], "dt": SMALL["dt"]})
    train_gradient(config)
    for name in ("config.json", "checkpoint.msgpack", "learning_curve.csv", "learning_curve.png", "summary.json"):
        assert (tmp_path / "a" / name).exists(), name
    ctrl, loaded = load_policy(tmp_path / "a")
    assert loaded == config
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["provenance"]["versions"]["jax"] == jax.__version__ and summary["updates"] == 4
    # the same 4 steps in process: the loaded controller acts exactly like the trained parameters
    cfg, plant = gradient_setup(config)
    init, chunk = objective.make_train(cfg, plant)
    state, m1 = chunk(init(jax.random.PRNGKey(0)))
    state, m2 = chunk(state)
    obj = np.concatenate([np.asarray(m1["objective"]), np.asarray(m2["objective"])])
    assert obj[-1] < obj[0], obj

    def actions(c):
        return np.asarray(simulate(plant, c, n_steps=40, record=Record(every=1)).trajectory.h)

    np.testing.assert_array_equal(actions(ctrl), actions(objective.make_controller(state.theta, cfg, plant)))
    # 2 steps, then --resume to 4: the same policy as 4 steps in one go
    half = config.updated(run={"out_dir": str(tmp_path / "b")}, grad={"grad_steps": 2})
    train_gradient(half)
    train_gradient(half.updated(grad={"grad_steps": 4}, run={"resume": True}))
    np.testing.assert_array_equal(actions(load_policy(tmp_path / "b")[0]), actions(ctrl))


def test_train_cli_gradient_defaults_come_from_the_library():
    config = config_from_args(["gradient", "--policy", "network"])
    cfg, _ = gradient_setup(config)
    assert config.run.out_dir == "runs/gradient-network"
    assert cfg == objective.GradientConfig.for_policy("network")
    assert gradient_setup(config_from_args(["gradient"]))[0] == objective.GradientConfig()
    # the gain bound is the gradient trainer's own (PPO's gain_max, per gain, does not apply; nor is it its flag)
    per_gain = TrainConfig.make(run={"algo": "gradient"}, env={"gain_max": (1.0, 2.0, 2.0)})
    assert gradient_setup(per_gain)[0] == objective.GradientConfig()
    assert gradient_setup(config_from_args(["gradient", "--grad-gain-max", "2"]))[0].grad_gain_max == 2.0
