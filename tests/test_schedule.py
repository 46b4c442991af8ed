"""The delay-scheduled gain law (``control.gain_law.scheduled_gains``), telling a controller its delay
(``control.tell_delay``), its gradient training (``--policy schedule``) and its place on the robustness map."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SMALL, check_told_delay_run
from extras import available

from jaxtraffic import TrafficParams, equilibrium, paper_initial_condition, simulate
from jaxtraffic.cli.train import config_from_args
from jaxtraffic.control import backstepping, constant_gains, schedule_gains, scheduled_gains, takes_delay, tell_delay
from jaxtraffic.learn.gradient import objective
from jaxtraffic.paper.scenarios import EvalConfig, robust_axis, run_robustness
from jaxtraffic.runs.gradient.policy import gradient_setup
from jaxtraffic.sim import Record

KNOTS = (0.0, 4.0, 8.0)
TABLE = jnp.asarray([[0.0, -1.0, -2.0], [0.2, -0.5, -1.0], [0.4, 0.0, -0.5]])
PLANT = TrafficParams(delay=2.0, **SMALL)  # 41 nodes, dt = 0.5 s


@pytest.mark.parametrize(("delay", "expected"), [(0.0, TABLE[0]), (2.0, (TABLE[0] + TABLE[1]) / 2), (4.0, TABLE[1]),
                                                 (7.0, TABLE[1] / 4 + 3 * TABLE[2] / 4), (12.0, TABLE[2])])
def test_schedule_interpolates_between_knots_and_holds_beyond_them(delay, expected):
    ctrl = scheduled_gains(TABLE, KNOTS, delay)
    np.testing.assert_allclose(np.asarray(schedule_gains(ctrl.settings)), np.asarray(expected), rtol=1e-6)


def test_a_flat_schedule_is_the_constant_gain_law():
    flat = scheduled_gains(jnp.tile(TABLE[1], (3, 1)), KNOTS, 5.0, filter_sigma=10.0, dx=float(PLANT.dx))
    const = constant_gains(*map(float, TABLE[1]), filter_sigma=10.0, dx=float(PLANT.dx))

    def h(c):
        return np.asarray(simulate(PLANT, c, n_steps=60, record=Record(every=1)).trajectory.h)

    np.testing.assert_array_equal(h(flat), h(const))


def test_bad_schedules_are_refused():
    with pytest.raises(ValueError, match="increase"):
        scheduled_gains(TABLE, (0.0, 4.0, 4.0))
    with pytest.raises(ValueError, match="table"):
        scheduled_gains(TABLE[:2], KNOTS)
    with pytest.raises(ValueError, match="not told a delay"):
        tell_delay(constant_gains(0.0, -1.0, -1.5), 4.0)


def test_tell_delay_sets_one_delay_or_a_batch():
    assert takes_delay(backstepping(4.0)) and takes_delay(scheduled_gains(TABLE, KNOTS))
    assert not takes_delay(constant_gains())
    one = tell_delay(scheduled_gains(TABLE, KNOTS), 2.0)
    np.testing.assert_allclose(np.asarray(schedule_gains(one.settings)), np.asarray((TABLE[0] + TABLE[1]) / 2))
    batch = tell_delay(scheduled_gains(TABLE, KNOTS), jnp.asarray([0.0, 4.0, 8.0]))
    assert batch.settings.table.shape == (3, 3, 3) and batch.settings.delay.shape == (3,)
    np.testing.assert_allclose(np.asarray(jax.vmap(schedule_gains)(batch.settings)), np.asarray(TABLE))
    bs = tell_delay(backstepping(4.0), jnp.asarray([1.0, 2.0]))
    assert bs.settings.k.shape == (2,) and np.asarray(bs.settings.delay).tolist() == [1.0, 2.0]
    with pytest.raises(ValueError, match="scalar or a"):
        tell_delay(backstepping(4.0), jnp.zeros((2, 2)))


def test_each_map_cell_is_told_its_plant_delay():
    """On the robustness map a schedule acts at every cell as the constant law of its plant delay's gains."""
    cfg = EvalConfig(n_points=SMALL["n_points"], dt=SMALL["dt"], robust_delays=robust_axis(3, 0.0, 8.0, SMALL["dt"]),
                     robust_alphas=(0.3,), robust_horizon_s=20.0, numerics_check=False)
    sched = scheduled_gains(TABLE, KNOTS, 4.0, filter_sigma=0.0)
    res = run_robustness({"grad_robust": sched}, cfg, log=lambda _: None)["grad_robust"]
    nom = cfg.nominal()
    n = round(20.0 / SMALL["dt"])
    rho0, v0 = paper_initial_condition(nom)  # the map starts every plant from the nominal target's perturbation
    for i, (d, gains) in enumerate(zip(cfg.robust_delays, TABLE, strict=True)):
        plant = nom.replace(delay=d, alpha=0.3)  # its own equilibrium is not the nominal target
        alone = simulate(plant, constant_gains(*map(float, gains)), n_steps=n, nominal=nom, rho0=rho0, v0=v0)
        np.testing.assert_allclose(res["final_rho_L2"][i, 0], float(alone.metrics["final_rho_L2"]), rtol=1e-5)
        # the offset: the final mean density minus the plant's own equilibrium density (at h_bar)
        offset = 1e3 * (float(jnp.mean(alone.final.rho)) - float(equilibrium(plant)[0]))  # veh/km
        np.testing.assert_allclose(res["final_rho_offset"][i, 0], offset, rtol=1e-4, atol=1e-5)


def test_schedule_gradient_matches_central_differences_and_stays_on_its_knots(x64):
    cfg = objective.GradientConfig(policy="schedule", schedule_knots=KNOTS, train_delays=(1.0, 3.0),
                                   train_alphas=(0.15, 0.3), train_horizon_s=40.0, record_every=10, reward_weight=0.0,
                                   waves_weight=1.0,
                                   comfort_weight=0.0, filter_sigma=0.0)
    scen = objective.training_scenarios(cfg, PLANT)

    def obj(theta):
        return objective.objective(theta, scen, objective.weights_of(cfg), cfg, PLANT)[0]

    theta = jnp.asarray(TABLE, jnp.float64)
    g = np.asarray(jax.grad(obj)(theta))
    eps = 1e-5
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        fd = (obj(theta.at[i, j].add(eps)) - obj(theta.at[i, j].add(-eps))) / (2 * eps)
        np.testing.assert_allclose(g[i, j], float(fd), rtol=1e-5, atol=1e-9)
        assert abs(g[i, j]) > 1e-5
    # no training delay lies beyond the knot at 4 s: the knot at 8 s cannot matter
    np.testing.assert_array_equal(g[2], np.zeros(3))


def test_default_training_plants_are_held_out_from_both_maps():
    config = config_from_args(["gradient", "--policy", "schedule"])
    cfg, _ = gradient_setup(config)
    assert cfg == objective.GradientConfig.for_policy("schedule") and config.run.out_dir == "runs/gradient-schedule"
    dt = float(TrafficParams().dt)
    maps = {"paper": (robust_axis(17, 0.0, 8.0, dt), robust_axis(12, 0.05, 0.6)),
            "reference": (robust_axis(9, 0.0, 8.0, dt), robust_axis(6, 0.05, 0.6))}
    for delays, alphas in maps.values():
        assert min(abs(d - m) for d in cfg.train_delays for m in delays) > 0.19
        assert min(abs(a - m) for a in cfg.train_alphas for m in alphas) >= 0.02
    # ... while they span the maps' ranges
    assert min(cfg.train_delays) < 0.5 and max(cfg.train_delays) > 7.5
    assert min(cfg.train_alphas) < 0.16 and max(cfg.train_alphas) > 0.55


def test_a_schedule_run_trains_saves_and_loads(tmp_path):

    out = tmp_path / "s"
    config = config_from_args(["gradient", "--policy", "schedule", "--out-dir", str(out), "--quiet",
                             "--n-points", "21", "--train-delays", "2,6", "--train-alphas", "0.15",
                             "--train-horizon-s", "10", "--grad-steps", "5", "--eval-horizon-s", "10",
                             *(["--tensorboard", str(tmp_path / "tb")] if available("tensorboardX") else [])])
    from jaxtraffic.runs.gradient.trainer import train_gradient

    train_gradient(config)
    if config.run.tensorboard:  # the gradient trainer writes its curve's rows as TensorBoard scalars too
        events = list((tmp_path / "tb").glob("*/events.out.tfevents.*"))  # (a folder per run)
        assert len(events) == 1 and b"train/objective" in events[0].read_bytes()
    check_told_delay_run(out, "schedule")
    assert '"knots_s"' in (out / "summary.json").read_text()


CEM_CFG = objective.GradientConfig(policy="schedule", grad_method="cem", schedule_knots=KNOTS, train_delays=(1.0, 5.0),
                                   train_alphas=(0.15, 0.3), train_horizon_s=30.0, record_every=10, steps_per_chunk=2,
                                   cem_population=6, filter_sigma=0.0, init_gains=(0.0, -1.0, -1.5))


def test_cem_fitness_is_the_maps_counts():
    """Stabilised and diverged counts of the fitness agree with rolling each scenario out on its own."""
    from jaxtraffic.learn.gradient import cem
    from jaxtraffic.sim.metrics import STABLE_STD

    n = objective.horizon_steps(CEM_CFG, PLANT.dt)
    thetas = jnp.stack([TABLE, jnp.tile(jnp.asarray([0.0, 3.0, 3.0]), (3, 1))])  # the second diverges somewhere
    fit, stab, div = cem.fitness(thetas, CEM_CFG, PLANT, n)
    scen = objective.training_scenarios(CEM_CFG, PLANT)
    for p, theta in enumerate(thetas):
        s = d = 0
        for i in range(scen.rho0.shape[0]):
            plant = jax.tree.map(lambda x, i=i: x[i], scen.params)
            res = simulate(plant, objective.make_controller(theta, CEM_CFG, PLANT, plant.delay), n_steps=n,
                           rho0=scen.rho0[i], v0=scen.v0[i], nominal=PLANT)
            gone = bool(res.metrics["diverged"])
            d += gone
            s += (not gone) and 1e3 * float(jnp.std(res.final.rho)) < STABLE_STD  # veh/km
        assert (int(stab[p]), int(div[p])) == (s, d)
    assert int(div[1]) > 0 and float(fit[0]) > float(fit[1])
    fit0, _, _ = cem.fitness(thetas, dataclasses.replace(CEM_CFG, cem_tie_weight=0.0), PLANT, n)  # counts alone
    np.testing.assert_array_equal(np.asarray(fit0), np.asarray(stab - cem.DIVERGED_COST * div, fit0.dtype))


def test_cem_mean_l2_fitness_is_the_fair_comparisons_measure():
    """With ``cem_fitness="mean_l2"`` the fitness is minus the mean over the scenarios of each rollout's time-averaged
    L2 (veh/km) as the fair comparison measures it (``compare.stats.per_scenario`` over the records, every 5 s of
    road), capped, a diverged rollout at the cap: the tuned baselines' fitness (``compare.tuning``)."""
    from jaxtraffic.compare import stats
    from jaxtraffic.learn.gradient import cem

    cfg = dataclasses.replace(CEM_CFG, cem_fitness="mean_l2")
    n = objective.horizon_steps(cfg, PLANT.dt)
    every = cem.record_every(n, float(PLANT.dt))
    assert every == round(stats.RECORD_EVERY_S / float(PLANT.dt)) and n % every == 0
    assert (cem.record_every(120, 0.1), cem.record_every(7, 0.1)) == (40, 7)  # lowered to a divisor of the horizon
    with pytest.raises(ValueError, match="recording period"):
        cem.fitness(jnp.stack([TABLE]), cfg, PLANT, n)
    thetas = jnp.stack([TABLE, jnp.tile(jnp.asarray([0.0, 3.0, 3.0]), (3, 1))])  # the second diverges somewhere
    fit, stab, div = cem.fitness(thetas, cfg, PLANT, n, every=every)
    scen = objective.training_scenarios(cfg, PLANT)
    for p, theta in enumerate(thetas):
        means = []
        for i in range(scen.rho0.shape[0]):
            plant = jax.tree.map(lambda x, i=i: x[i], scen.params)
            res = simulate(plant, objective.make_controller(theta, cfg, PLANT, plant.delay), n_steps=n,
                           rho0=scen.rho0[i], v0=scen.v0[i], nominal=PLANT, record=Record(every=every))
            t = np.append(np.asarray(res.trajectory.t), n * float(PLANT.dt))
            l2 = np.append(np.asarray(res.trajectory.rho_L2), float(res.metrics["final_rho_L2"]))[None]
            per = stats.per_scenario(t, l2, np.asarray([res.metrics["diverged"]]), {j: [0.0] for j in stats.JS})
            means.append(min(float(per["mean_rho_L2"][0]), stats.L2_CAP))
        np.testing.assert_allclose(float(fit[p]), -np.mean(means), rtol=2e-5)
    assert int(div[1]) > 0 and float(fit[0]) > float(fit[1])  # the counts are still reported
    init, chunk = cem.make_train(cfg, PLANT)  # and it trains: the policy's fitness never falls
    state, m = chunk(init(jax.random.PRNGKey(0)))
    assert np.all(np.diff(np.asarray(m["objective"])) <= 0) and np.isfinite(float(state.fitness))


def test_cem_keeps_its_best_and_is_deterministic():
    from jaxtraffic.learn.gradient import cem

    init, chunk = cem.make_train(CEM_CFG, PLANT)
    s1, m1 = chunk(init(jax.random.PRNGKey(3)))
    s2, m2 = chunk(init(jax.random.PRNGKey(3)))
    np.testing.assert_array_equal(np.asarray(s1.theta), np.asarray(s2.theta))
    obj = np.asarray(m1["objective"])
    assert np.all(np.diff(obj) <= 0) and int(s1.update) == 2  # the best so far never gets worse
    np.testing.assert_array_less(np.full((3, 3), cem.SIGMA_MIN - 1e-7), np.asarray(s1.sigma))
    with pytest.raises(ValueError, match="cem"):
        objective.GradientConfig(policy="network", grad_method="cem")


def test_oracle_rows_pick_what_they_promise():
    """Best constant, best per delay row, best per cell, from made-up results of 3 gain triples on a 2 x 2 map."""
    from jaxtraffic.paper.oracle import oracle_rows, stabilised_and_diverged

    s, w = 0.1, 5.0  # a stabilised cell's std and a wavy one's (veh/km)
    std = np.array([[[s, s], [w, w]],    # triple 0: row 0 only
                    [[w, w], [s, w]],    # triple 1: one cell of row 1
                    [[s, w], [w, s]]])   # triple 2: one cell of each row
    div = np.zeros_like(std, bool)
    div[0, 1, 1] = True                  # triple 0 also diverges at (1, 1)
    rows = oracle_rows([(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2.0, 2.0, 2.0)], div, std)
    # triples 0 and 2 both stabilise 2 cells; 2 diverges nowhere
    assert rows["best_constant"]["gains"] == [2.0, 2.0, 2.0]
    assert stabilised_and_diverged(rows["best_constant"]) == (2, 0)
    assert rows["delay_schedule"]["gains"] == [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]  # row 1: a tie, the first kept
    assert stabilised_and_diverged(rows["delay_schedule"]) == (3, 0)
    assert stabilised_and_diverged(rows["per_cell"]) == (4, 0)
