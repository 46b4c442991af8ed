"""Issue 47, item 5: the learned laws train on the scenario distribution's train split (``EnvConfig.train_split``:
PPO's episodes, the gradient trainers' scenarios) and the held-out verdicts over seeds (``compare.verdicts``)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.compare import ScenarioDistribution, sample, verdicts
from jaxtraffic.compare.scenarios import EpisodePool
from jaxtraffic.learn.env import env_params, reset_env
from jaxtraffic.learn.env_config import EnvConfig
from jaxtraffic.learn.gradient import cem, objective
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.runs.config import TrainConfig

PLANT = jt.TrafficParams(n_points=21, delay=4.0)


def test_the_pool_is_the_train_split_and_shares_nothing_with_the_test_split():
    pool = EpisodePool.train_split(12, PLANT)
    train = sample(ScenarioDistribution(), "train", 12, 0, base=PLANT)
    test = sample(ScenarioDistribution(), "test", 256, 0, base=PLANT)
    np.testing.assert_allclose(np.asarray(pool.rho0), train.rho0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pool.delay), train.draws["delay"], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pool.alpha), train.draws["alpha"], rtol=1e-6)
    # no initial state of the pool is one of the test split's
    dist = np.abs(np.asarray(pool.rho0)[:, None, :] - test.rho0[None]).max(axis=-1)
    assert dist.min() > 1e-4


def test_ppo_episodes_are_drawn_from_the_pool_and_the_default_keeps_the_ranges():
    ep = env_params(EnvConfig(train_split=5), PLANT)
    assert ep.pool is not None and ep.pool.rho0.shape == (5, 21)
    _, state = jax.vmap(reset_env, (0, None))(jax.random.split(jax.random.key(3), 64), ep)
    rho0 = np.asarray(state.plant.rho)
    # every episode starts at one of the pool's scenarios: its plant and its initial density
    match = np.abs(rho0[:, None, :] - np.asarray(ep.pool.rho0)[None]).max(axis=-1).argmin(axis=1)
    np.testing.assert_allclose(rho0, np.asarray(ep.pool.rho0)[match], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(state.plant_params.delay), np.asarray(ep.pool.delay)[match], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(state.plant_params.alpha), np.asarray(ep.pool.alpha)[match], rtol=1e-6)
    assert len(set(match.tolist())) == 5  # 64 draws reach all five
    assert env_params(EnvConfig(), PLANT).pool is None  # the default: the ranges, as before


def test_the_gradient_trainers_read_the_same_split_through_the_run_config():
    config = TrainConfig.make(plant={"n_points": 21}, env={"train_split": 4})
    assert config.grad.train_split == 4 and config.grad.n_scenarios == 4
    scen = objective.training_scenarios(config.grad, config.plant)
    pool = EpisodePool.train_split(4, config.plant)
    np.testing.assert_array_equal(np.asarray(scen.rho0), np.asarray(pool.rho0))
    np.testing.assert_array_equal(np.asarray(scen.params.delay), np.asarray(pool.delay))
    # the CEM trainer runs compiled on them (the pool drawn on the host, passed traced)
    grad = GradientConfig.for_policy("schedule", train_split=4, grad_steps=1, steps_per_chunk=1, cem_population=2,
                                     train_horizon_s=2.0, record_every=1)
    init, chunk = cem.make_train(grad, config.plant)
    state, metrics = chunk(init(jax.random.key(0)))
    assert int(state.update) == 1 and 0 <= int(metrics["stabilised"][0]) <= 4


def _rows(med: dict[str, float], n: int = 40, diverged: dict[str, int] | None = None) -> dict:
    rng = np.random.default_rng(0)
    out = {}
    for k, m in med.items():
        x = m * np.exp(0.05 * rng.standard_normal(n))
        div = np.zeros(n, bool)
        div[:(diverged or {}).get(k, 0)] = True
        x = np.where(div, np.inf, x)
        out[k] = {"mean_rho_L2": x, "diverged": div, "not_settled": div.copy()}
    return out


def test_the_verdicts_take_the_median_seed_and_judge_the_frontier_paired():
    res = _rows({"base": 2.0, "law_s0": 1.0, "law_s1": 3.0, "law_s2": 1.4, "wave": 1.2}, diverged={"law_s1": 2})
    groups = verdicts.seed_groups(list(res), "_s")
    assert groups == {"law": ["law_s0", "law_s1", "law_s2"]}
    assert verdicts.median_seed(res, groups["law"]) == "law_s2"
    lines, over = verdicts.seed_lines(res, groups, str)
    assert over["law"]["diverged"] == [0, 2, 0] and over["law"]["spread"][0] == pytest.approx(1.0, rel=0.05)
    _, best = verdicts.frontier(res, ["law_s2"], ["base"], str)
    assert best["ratio"] == pytest.approx(0.7, rel=0.1) and best["ratio_ci95"][1] < 0.8 and best["frontier"]
    _, worse = verdicts.frontier(res, ["law_s1"], ["base"], str)  # 1.5x and two failures more: not reached
    assert worse["ratio"] > 1 and not worse["frontier"]
    _, checks = verdicts.base_checks(res, {"law": "base"}, lambda r: r.split("_s")[0], str)
    assert checks == {"law_s0_vs_base": True, "law_s1_vs_base": False, "law_s2_vs_base": True}


def test_the_frontier_is_the_ratio_of_the_medians_with_the_intervals_apart_and_no_more_failures():
    """Issue 47's definition, not the median of per-scenario ratios: a law whose median is 2/3 of the rival's, with
    the two medians' intervals apart and as many failures, reaches it although its per-scenario median ratio is
    0.975; an overlap of the intervals, or more scenarios left unsettled, and it is not reached."""
    model = np.tile([1.0, 2.0, 3.0, 4.0, 5.0], 50)
    law = np.tile([2.0, 1.9, 0.1, 3.9, 4.9], 50)
    ok = np.zeros(250, bool)
    res = {"law": {"mean_rho_L2": law, "diverged": ok, "not_settled": ok},
           "model": {"mean_rho_L2": model, "diverged": ok, "not_settled": ok}}
    lines, best = verdicts.frontier(res, ["law"], ["model"], str)
    assert best["ratio"] == pytest.approx(2.0 / 3.0) and best["intervals_apart"] and best["frontier"]
    assert best["ratio_per_scenario"] == pytest.approx(0.975) and "**reached**" in lines[0]
    unsettled = {**res, "law": {**res["law"], "not_settled": np.arange(250) < 1}}
    assert not verdicts.frontier(unsettled, ["law"], ["model"], str)[1]["frontier"]
    wide = {"law": res["law"], "model": {**res["model"], "mean_rho_L2": np.tile([2.0, 4.0], 125)}}
    _, close = verdicts.frontier(wide, ["law"], ["model"], str)  # ratio 2/3 again; the rival's median in [2, 4]
    assert close["ratio"] == pytest.approx(2.0 / 3.0) and not close["intervals_apart"] and not close["frontier"]
    worse = {"law": res["model"], "model": res["law"]}  # apart the other way: 1.5x, not reached
    _, behind = verdicts.frontier(worse, ["law"], ["model"], str)
    assert behind["ratio"] == pytest.approx(1.5) and behind["intervals_apart"] and not behind["frontier"]


def test_the_frontier_meets_the_best_law_told_no_more_than_d_not_the_information_bound():
    """``paper.fair.tables``: the information bound (told the plant's alpha) is best here, but the learned law is
    judged against the best model-based law told D at most (the tuned adaptive law)."""
    from jaxtraffic.compare.stats import MEASURES
    from jaxtraffic.paper import fair

    res = _rows({"backstepping": 5.0, "backstepping_alpha": 0.5, "adaptive_backstepping_tuned": 2.0,
                 "grad_robust_split_s0": 1.0})
    for r in res.values():  # the table's other measures (the frontier reads mean_rho_L2 and diverged)
        r.update({m: r["mean_rho_L2"] for m in MEASURES if m not in r})
    _, _, checks = fair.tables(res, {k: k for k in res})
    assert checks["best_model_based"] == "adaptive_backstepping_tuned"
    assert checks["ratio"] == pytest.approx(0.5, rel=0.1) and checks["frontier"]


def test_the_sweeps_cem_laws_are_trained_as_the_baselines_are_tuned():
    """benchmarks/train_split_sweep.py trains its CEM laws (delay schedule, residual) with the tuned baselines'
    budget, scenarios and fitness (``compare.tuning.tune``'s defaults, ``benchmarks/tune_baselines.py``'s split):
    the same population, generations and initial spread, the same train scenarios and horizon, and the fair
    comparison's time-averaged L2 as the fitness, not the maps' counts; its matched PPO budget is their
    plant-seconds."""
    import inspect
    import sys
    from pathlib import Path

    from jaxtraffic.cli.train import config_from_args
    from jaxtraffic.compare import tuning

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import train_split_sweep
    import tune_baselines

    tune_default = {k: p.default for k, p in inspect.signature(tuning.tune).parameters.items()}
    grads = {law: config_from_args([algo, "--recipe", recipe, *extra]).grad
             for law, (algo, recipe, extra) in train_split_sweep.PLAN.items() if algo == "gradient"}
    cem_laws = {law: g for law, g in grads.items() if g.grad_method == "cem"}
    assert set(cem_laws) == {"grad_robust", "grad_residual"}
    for law, g in cem_laws.items():
        assert g.cem_fitness == "mean_l2", law
        assert (g.cem_population, g.grad_steps, g.cem_sigma) == (
            tune_default["population"], tune_default["generations"], tune_default["sigma"]), law
        assert (g.train_split, g.train_horizon_s) == (tune_baselines.N_TRAIN, tune_baselines.HORIZON_S), law
    # PPO's checkpoints are selected on the same split, horizon and plant (make_split_suite, the paper grid)
    algo, recipe, extra = train_split_sweep.PLAN["ppo"]
    ppo = config_from_args([algo, "--recipe", recipe, *extra])
    # --ppo-steps MATCHED_PPO_STEPS gives PPO the CEM classes' budget in plant-seconds (rollouts x horizon)
    for law, g in cem_laws.items():
        plant_s = g.cem_population * g.grad_steps * g.train_split * g.train_horizon_s
        assert train_split_sweep.MATCHED_PPO_STEPS * ppo.plant.dt == pytest.approx(plant_s), law
    assert (ppo.env.train_split, ppo.run.val_horizon_s, ppo.run.val_plant, ppo.plant.n_points) == (
        tune_baselines.N_TRAIN, tune_baselines.HORIZON_S, "training", 201)
    pool = EpisodePool.train_split(tune_baselines.N_TRAIN, PLANT)  # the trainers' scenarios are the tuning's
    tuned = sample(ScenarioDistribution(), "train", tune_baselines.N_TRAIN, tune_baselines.SEED, base=PLANT)
    np.testing.assert_allclose(np.asarray(pool.rho0), tuned.rho0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pool.delay), tuned.draws["delay"], rtol=1e-6)


def test_ppo_split_runs_are_selected_on_their_train_split_by_the_comparisons_measure():
    """A PPO run trained on the train split scores its checkpoints on its own training scenarios (``selection.
    make_split_suite``) with the held-out comparison's measure: a member's score equals the capped mean over the
    scenarios of ``compare.evaluate_laws``' time-averaged L2, over backstepping's (told each D), computed here by
    the comparison's own code; the paper's wave is none of the scenarios."""
    from jaxtraffic.compare import LawSpec, evaluate_laws
    from jaxtraffic.compare.stats import L2_CAP
    from jaxtraffic.control.baselines import backstepping, lyapunov
    from jaxtraffic.runs.ppo.selection import make_split_suite
    from jaxtraffic.sim.initial import paper_initial_condition

    n, horizon = 4, 20.0
    suite = make_split_suite(PLANT, horizon, n)
    assert suite.scenarios == {"train_split": n, "seed": 0, "horizon_s": horizon}
    members = jax.tree.map(lambda *x: np.stack(x), lyapunov(0.5), lyapunov(1.5))
    out = suite(members, 2)
    scen = sample(ScenarioDistribution(), "train", n, 0, base=PLANT)
    np.testing.assert_allclose(scen.rho0, np.asarray(EpisodePool.train_split(n, PLANT).rho0), rtol=1e-6)
    paper, _ = paper_initial_condition(PLANT)
    assert np.abs(scen.rho0 - np.asarray(paper)[None]).max(axis=1).min() > 1e-4  # not the paper's wave
    res = evaluate_laws([LawSpec("a", "a", lambda: lyapunov(0.5)), LawSpec("b", "b", lambda: lyapunov(1.5)),
                         LawSpec("ref", "ref", backstepping, "delay")], scen, PLANT, horizon, log=lambda _: None)
    capped = {k: np.minimum(r["mean_rho_L2"], L2_CAP) for k, r in res.items()}
    np.testing.assert_allclose(suite.reference["mean_rho_L2"], capped["ref"], rtol=1e-6)
    want = np.array([capped["a"].mean(), capped["b"].mean()]) / capped["ref"].mean()
    np.testing.assert_allclose(out["score"], want, rtol=1e-6)
    assert out["ratio"].shape == (2, n) and out["score"][0] != out["score"][1]
    # trained under sensor noise (EnvConfig.train_sensor_noise): every law, the reference too, sees each scenario
    # through its level and key, as the comparison's --sensor-noise has it
    noisy = sample(ScenarioDistribution(sensor_noise_range=(0.05, 0.1)), "train", n, 0, base=PLANT)
    res = evaluate_laws([LawSpec("a", "a", lambda: lyapunov(0.5)), LawSpec("ref", "ref", backstepping, "delay")],
                        noisy, PLANT, horizon, log=lambda _: None)
    capped = {k: np.minimum(r["mean_rho_L2"], L2_CAP) for k, r in res.items()}
    seen = make_split_suite(PLANT, horizon, n, sensor_noise=(0.05, 0.1))
    np.testing.assert_allclose(seen.reference["mean_rho_L2"], capped["ref"], rtol=1e-5)
    np.testing.assert_allclose(seen(jax.tree.map(lambda x: x[:1], members), 1)["score"],
                               capped["a"].mean() / capped["ref"].mean(), rtol=1e-5)
    assert not np.allclose(capped["ref"], suite.reference["mean_rho_L2"], rtol=1e-4)  # the noise is seen


def test_a_ppo_split_run_validates_without_the_paper_rule(tmp_path):
    """The PPO trainer of a split run builds the split suite and validates members whose evaluation on the paper's
    wave fails the paper's rule (a default run ranks those below every validated one, by reward, unvalidated)."""
    from jaxtraffic.runs.ppo import selection
    from jaxtraffic.runs.ppo.trainer import PPOTraining, build

    def trainer(split: int) -> PPOTraining:
        config = TrainConfig.make(plant={"n_points": 21, "delay": 1.0, "max_delay_steps": 80},
                                  env={"train_split": split, "horizon_s": 2.0},
                                  ppo={"num_envs": 4, "num_steps": 4, "num_minibatches": 1, "update_epochs": 1},
                                  run={"val_horizon_s": 10.0, "val_plant": "training", "min_wave_speed": None,
                                       "require_certificate": False})
        t = PPOTraining(config, *build(config), tmp_path)
        t.start(None, lambda *_: None)
        return t

    ev = {"final_reward": np.array([-1e3, -1e3]), "diverged": np.array([False, False]),
          "wave_speed": np.zeros(2)}
    split = trainer(3)
    assert split.suite is not None and split.suite.scenarios["train_split"] == 3
    paper, _, score = split._judge(ev)
    assert not paper.any() and np.all(score < selection.UNVALIDATED / 2)  # validated: the suite's scores
    _, _, score = trainer(0)._judge(ev)
    assert np.all(score > selection.UNVALIDATED / 2)  # a default run: not validated


def test_a_split_run_that_validates_nothing_keeps_the_checkpoint_best_on_its_train_split(tmp_path):
    """Issue 47: a split run none of whose evaluations passes the wave-speed and certificate test ranks its members
    by their own suite score on the train split (below every validated one), never by their reward on the paper's
    wave; a default run keeps ranking those by reward."""
    from jaxtraffic.runs.ppo import selection
    from jaxtraffic.runs.ppo.trainer import PPOTraining, build, member_controller

    suite = lambda controller, n: {"score": np.array([2.0, 1.0])}  # noqa: E731  (member 1 best on the split)
    reward = np.array([-0.01, -5.0])  # member 0 best on the paper's wave
    none = np.array([False, False])
    by_wave = selection.scores(reward, none, suite, lambda: None)
    by_split = selection.scores(reward, none, suite, lambda: None, rank_all=True)
    assert np.argmin(by_wave) == 0 and np.argmin(by_split) == 1
    assert all(selection.Validation.of(s) is selection.Validation.NOT_VALIDATED for s in by_split)
    one = selection.scores(reward, np.array([True, False]), suite, lambda: None, rank_all=True)
    assert one[0] == 2.0 and one[1] > selection.UNVALIDATED  # a validated member still ranks first
    text = selection.best_text(float(by_split[1]), 1, 64, "the mean ratio", rank_all=True)
    assert "the best by the mean ratio" in text and "evaluation reward" not in text

    config = TrainConfig.make(plant={"n_points": 21, "delay": 1.0, "max_delay_steps": 80},
                              env={"train_split": 3, "horizon_s": 2.0},
                              ppo={"num_envs": 4, "num_steps": 4, "num_minibatches": 1, "update_epochs": 1},
                              run={"val_horizon_s": 10.0, "val_plant": "training", "min_wave_speed": 1e3,
                                   "require_certificate": False})
    t = PPOTraining(config, *build(config), tmp_path)
    t.start(None, lambda *_: None)
    ev = {"final_reward": np.array([-1e-3, -1e3]), "diverged": np.array([False, False]), "wave_speed": np.zeros(2)}
    _, ok, score = t._judge(ev)  # no member is fast enough: none validated
    assert not ok.any() and np.all(score > selection.UNVALIDATED)
    own = t.suite(member_controller(t.ppo_config, t.env_params, t.rep.params, t.rep.stats.mean, t.rep.stats.var),
                  2)["score"]
    np.testing.assert_allclose(score - selection.UNVALIDATED, own, rtol=1e-6)


def test_the_sweep_resumes_an_interrupted_run_and_skips_a_finished_one(tmp_path):
    """An interrupted run writes its summary too (``interrupted``: true): the sweep must resume it, not count it
    as done (it did, and a seed stopped at 2 M of its 13 M environment steps was judged as trained)."""
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from train_split_sweep import finished

    assert not finished(tmp_path)  # nothing yet
    (tmp_path / "summary.json").write_text(json.dumps({"env_steps": 2073600, "interrupted": True}))
    assert not finished(tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps({"env_steps": 12979200, "interrupted": False}))
    assert finished(tmp_path)



def test_the_gradient_trainers_see_the_train_splits_sensor_noise_as_the_comparison_does():
    """``GradientConfig.train_sensor_noise``: the pool carries the split's noise levels and keys (the scenarios are
    those of a noise-free split), the CEM fitness of a law under that noise is the comparison's measure of the same
    law on the same scenarios (``compare.protocol``: its own path, told each D, the noise wrapped there), the noise
    moves it, Adam's objective has a finite gradient under it, and a noise range without a split is refused."""
    from jaxtraffic.compare import protocol, stats
    from jaxtraffic.control.adapter import ControllerGrid

    dist = ScenarioDistribution(sensor_noise_range=(0.05, 0.1))
    scen = sample(dist, "train", 4, 0, base=PLANT)
    pool = EpisodePool.train_split(4, PLANT, (0.05, 0.1))
    np.testing.assert_allclose(np.asarray(pool.noise), scen.noise_levels(), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(pool.keys), np.asarray(scen.keys()))
    np.testing.assert_array_equal(np.asarray(pool.rho0), np.asarray(EpisodePool.train_split(4, PLANT).rho0))
    assert np.all((scen.noise_levels() >= 0.05) & (scen.noise_levels() <= 0.1))

    thetas = jnp.stack([jnp.tile(jnp.asarray([0.0, -1.0, -1.5]), (5, 1)), jnp.tile(jnp.asarray([0.3, -0.5, -1.0]),
                                                                                    (5, 1))])
    fine = PLANT.replace(n_points=41)
    for plant, points in ((PLANT, 0), (fine, 21)):  # the law on the plant's grid, and on a coarser one of its own
        grad = GradientConfig.for_policy("schedule", train_split=4, cem_population=2, train_horizon_s=10.0,
                                         record_every=1, cem_fitness="mean_l2", train_sensor_noise=(0.05, 0.1),
                                         controller_points=points)
        n_steps, every = protocol.steps_of(10.0, float(plant.dt))
        fit, _, _ = cem.fitness(thetas, grad, plant, n_steps, EpisodePool.train_split(4, plant, (0.05, 0.1)), every)
        laws = [protocol.LawSpec(f"p{i}", "", lambda th=th, g=grad: objective.own_controller(th, g, 21, 50.0), "delay",
                                 ControllerGrid(21, float(plant.dt), plant.max_delay_steps) if points else None)
                for i, th in enumerate(thetas)]
        res = protocol.evaluate_laws(laws, sample(dist, "train", 4, 0, base=plant), plant, 10.0, log=lambda s: None,
                                     release=False)
        want = [-float(np.mean(stats.capped(res[f"p{i}"]["mean_rho_L2"]))) for i in range(2)]
        np.testing.assert_allclose(np.asarray(fit), want, rtol=1e-5)
    grad = dataclasses.replace(grad, controller_points=0)
    n_steps, every = protocol.steps_of(10.0, float(PLANT.dt))
    fit, _, _ = cem.fitness(thetas, grad, PLANT, n_steps, pool, every)
    quiet = dataclasses.replace(grad, train_sensor_noise=(0.0, 0.0))
    fit0, _, _ = cem.fitness(thetas, quiet, PLANT, n_steps, EpisodePool.train_split(4, PLANT), every)
    assert np.all(np.abs(np.asarray(fit0) - np.asarray(fit)) > 1e-6)

    adam = GradientConfig(train_split=2, train_horizon_s=2.0, record_every=5, train_sensor_noise=(0.05, 0.1))
    scen2, w = objective.training_scenarios(adam, PLANT), objective.weights_of(adam)
    loss, g = jax.value_and_grad(lambda t: objective.objective(t, scen2, w, adam, PLANT)[0])(jnp.asarray([-0.3, -0.6,
                                                                                                          -0.6]))
    assert np.isfinite(float(loss)) and np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).sum()) > 0
    with pytest.raises(ValueError, match="train_sensor_noise"):
        objective.training_scenarios(GradientConfig(train_sensor_noise=(0.0, 0.05)), PLANT)
    with pytest.raises(ValueError, match="train_sensor_noise"):
        GradientConfig(train_sensor_noise=(0.1, 0.05))
