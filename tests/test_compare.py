"""The fair comparison (jaxtraffic.compare): the split's draws (seeded, independent, physical), the measures
against oracle series, the bootstrap interval, the measurement filter, and the protocol on a tiny grid: each law
does what its theory says on held-out scenarios."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.compare import (
    LawSpec,
    ScenarioDistribution,
    bootstrap_interval,
    delay_order,
    evaluate_laws,
    median_ratio,
    per_scenario,
    sample,
    settle_times,
    summarise,
    summary_table,
    wilson_interval,
)
from jaxtraffic.control import adaptive_backstepping, measurement_filter, tell_delay

TINY = jt.TrafficParams(n_points=21, dt=0.5, max_delay_steps=20)
DIST = ScenarioDistribution()


def test_the_splits_are_seeded_independent_and_physical():
    a, b = sample(DIST, "test", 64, seed=3, base=TINY), sample(DIST, "test", 64, seed=3, base=TINY)
    np.testing.assert_array_equal(a.rho0, b.rho0)
    np.testing.assert_array_equal(a.key_of(), b.key_of())
    train = sample(DIST, "train", 64, seed=3, base=TINY)
    assert not (a.key_of()[:, None, :] == train.key_of()[None]).all(-1).any()  # no test scenario is a train one
    assert not np.array_equal(a.rho0, sample(DIST, "test", 64, seed=4, base=TINY).rho0)
    assert np.all(a.rho0 > 0) and np.all(a.rho0 < 1 / TINY.l)
    np.testing.assert_allclose(a.rho0 * a.v0, TINY.q_in, rtol=1e-12)  # v = q_in / rho: the paper's construction
    d = a.draws
    assert set(np.unique(d["kind"])) == {0, 1, 2} and 0 < d["own"].mean() < 1
    assert DIST.delay_range[0] <= d["delay"].min() and d["delay"].max() <= DIST.delay_range[1]
    np.testing.assert_allclose(np.asarray(a.plants.delay), d["delay"])  # whole steps, recorded as run
    np.testing.assert_allclose(d["delay"] / TINY.dt, np.round(d["delay"] / TINY.dt), atol=1e-9)
    dev = np.abs(a.rho0 - a.rho0.mean(axis=1, keepdims=True)).max(axis=1) * 1e3  # veh/km
    assert dev.max() <= 2 * DIST.amp_range[1]
    with pytest.raises(ValueError, match="split must be one of"):
        sample(DIST, "validation", 4)
    with pytest.raises(ValueError, match="beyond the plant's buffer"):
        sample(DIST, "test", 4, base=TINY.replace(max_delay_steps=4))
    with pytest.raises(ValueError, match="amp_range"):
        ScenarioDistribution(amp_range=(5.0, -1.0))


def test_settling_time_late_maximum_and_time_average_against_oracles():
    t = np.linspace(0.0, 100.0, 101)
    decay = 20.0 * np.exp(-t / 20.0)  # veh/km: below 10 % of its start after 20 ln 10 = 46.05 s
    bump = decay.copy()
    bump[80] = 10.0  # back above the threshold at 80 s: settled only from 81 s
    grows = 20.0 * np.exp(t / 200.0)
    got = settle_times(t, np.stack([decay, bump, grows]))
    np.testing.assert_allclose(got, [47.0, 81.0, np.inf])
    assert settle_times(t, decay[None], threshold=1e3)[0] == 0.0  # always below: its first time
    per = per_scenario(t, np.stack([decay, bump, grows]), np.array([False, False, True]),
                       {j: np.ones(3) for j in ("J_TTT", "J_fuel", "J_comfort")})
    exact = 20.0 * 20.0 * (1 - np.exp(-5.0)) / 100.0  # veh/km: time average of 20 e^{-t/20} over [0, 100]
    assert per["mean_rho_L2"][0] == pytest.approx(exact, rel=1e-3)
    assert per["late_max_rho_L2"][0] == pytest.approx(20.0 * np.exp(-50.0 / 20.0))
    assert per["late_max_rho_L2"][1] == pytest.approx(10.0)
    assert np.all(np.isinf([per[k][2] for k in ("mean_rho_L2", "settle_s", "J_comfort")]))  # diverged: worst
    assert per["not_settled"].tolist() == [False, False, True]


def test_the_bootstrap_interval_is_seeded_covers_and_shrinks():
    rng = np.random.default_rng(0)
    misses, widths = 0, []
    for trial in range(200):  # the median of a standard normal is 0: a 95 % interval misses it ~5 % of the time
        lo, hi = bootstrap_interval(rng.normal(size=101), n_boot=400, seed=trial)
        misses += not (lo <= 0.0 <= hi)
        widths.append(hi - lo)
    assert 2 <= misses <= 20
    x = rng.normal(size=400)
    assert bootstrap_interval(x, seed=1) == bootstrap_interval(x, seed=1)
    assert np.subtract(*bootstrap_interval(x)[::-1]) < 0.6 * np.mean(widths)  # 4x the samples: about half as wide
    with pytest.raises(ValueError, match="non-empty 1-d"):
        bootstrap_interval(np.zeros((2, 2)))


def test_summaries_rank_failures_last_and_pair_the_ratio():
    base = {"mean_rho_L2": np.array([1.0, 2.0, 4.0, np.inf]), "diverged": np.array([False, False, False, True])}
    half = {"mean_rho_L2": base["mean_rho_L2"] / 2, "diverged": base["diverged"]}
    full = {k: v for k, v in base.items()}
    for per in (base, half, full):
        for m in ("late_max_rho_L2", "settle_s", "J_TTT", "J_fuel", "J_comfort"):
            per.setdefault(m, per["mean_rho_L2"])
        per.setdefault("not_settled", per["diverged"])
    s = summarise(half, reference=base)
    assert s["mean_rho_L2"]["median"] == 1.5  # an even count: the mean of the middle two, (1 + 2) / 2
    assert s["ratio_mean_rho_L2"]["value"] == pytest.approx(0.5)  # the ratio of the medians, 1.5 / 3
    assert s["diverged_rate"]["value"] == 0.25 and s["n"] == 4
    assert s["mean_rho_L2"]["unit"] == "veh/km"
    assert summarise(base)["late_max_rho_L2"]["median"] == 3.0
    two_failed = {**base, "mean_rho_L2": np.array([1.0, 2.0, np.inf, np.inf])}
    assert summarise(two_failed)["mean_rho_L2"]["median"] == np.inf  # a failure in the middle: the median fails


def test_the_failure_rates_have_wilson_intervals_not_empty_at_zero_or_all():
    """Oracle values of the Wilson score interval (95 %): 0 of 10 -> [0, 0.2775], 5 of 10 -> [0.2366, 0.7634],
    10 of 10 -> [0.7225, 1]; a percentile bootstrap gives [0, 0] at 0 of n."""
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.27753), abs=1e-5)
    assert wilson_interval(5, 10) == pytest.approx((0.23659, 0.76341), abs=1e-5)
    assert wilson_interval(10, 10) == pytest.approx((0.72247, 1.0), abs=1e-5)
    lo, hi = wilson_interval(0, 256)
    assert lo == 0.0 and 0.0 < hi < 0.02
    with pytest.raises(ValueError, match="0 <= k <= n"):
        wilson_interval(3, 2)


def test_the_ratio_of_medians_is_paired_and_bounds_its_value():
    """``median_ratio``: median(a) / median(b) with an interval from resampling the scenarios together; a law
    that is exactly half of another on every scenario has 0.5 [0.5, 0.5] however the scenarios spread."""
    b = np.random.default_rng(0).lognormal(size=64)
    assert median_ratio(b / 2, b) == (pytest.approx(0.5), (pytest.approx(0.5), pytest.approx(0.5)))
    r, (lo, hi) = median_ratio(np.random.default_rng(1).lognormal(size=64), b)
    assert lo <= r <= hi and r == pytest.approx(np.median(np.random.default_rng(1).lognormal(size=64)) / np.median(b))
    with pytest.raises(ValueError, match="one shape"):
        median_ratio(b, b[:3])


def test_the_measurement_filter_is_the_gain_laws_own_filter():
    p = jt.TrafficParams(n_points=41, delay=1.0, dt=0.25, max_delay_steps=8)
    dx = float(p.dx)
    own = jt.simulate(p, jt.constant_gains(0.0, -0.5, -1.0, filter_sigma=60.0, dx=dx), n_steps=120)
    wrapped = jt.simulate(p, measurement_filter(jt.constant_gains(0.0, -0.5, -1.0), 60.0, dx=dx), n_steps=120)
    np.testing.assert_allclose(np.asarray(own.final.rho), np.asarray(wrapped.final.rho), rtol=1e-5)
    bs = measurement_filter(jt.backstepping(1.0), 60.0, dx=dx)  # any law: told a delay like the law itself
    assert float(tell_delay(bs, 2.0).settings.delay) == 2.0 and "sigma 60 m" in bs.name
    assert measurement_filter(jt.lyapunov(1.0), 0.0).name == "lyapunov"
    pointwise = jt.simulate(p, jt.backstepping(1.0), n_steps=120)
    assert not np.allclose(np.asarray(pointwise.final.rho), np.asarray(jt.simulate(p, bs, n_steps=120).final.rho))


def test_on_held_out_scenarios_the_laws_do_what_their_theory_says():
    """On the test split (tiny grid, 300 s): backstepping told each plant's delay diverges on no more scenarios
    than Lyapunov, which does not compensate it; the adaptive law, which also estimates alpha, settles where the
    others leave a wave, and beats backstepping's time-averaged L2 with a paired interval below 1."""
    scen = sample(DIST, "test", 24, seed=0, base=TINY)
    laws = [LawSpec("lyapunov", "Lyapunov", lambda: jt.lyapunov(1.0)),
            LawSpec("backstepping", "backstepping", lambda: jt.backstepping(4.0), told="delay"),
            LawSpec("adaptive", "adaptive", lambda: adaptive_backstepping(4.0), told="delay")]
    res = evaluate_laws(laws, scen, TINY, horizon_s=300.0, record_every_s=5.0, chunk=16, log=lambda s: None)
    assert set(res) == {"lyapunov", "backstepping", "adaptive"} and res["adaptive"]["mean_rho_L2"].shape == (24,)
    assert res["backstepping"]["diverged"].sum() <= res["lyapunov"]["diverged"].sum()
    lines, summ = summary_table(res, {s.name: s.label for s in laws}, reference="backstepping")
    assert summ["adaptive"]["ratio_mean_rho_L2"]["ci95"][1] < 1.0
    assert summ["adaptive"]["not_settled_rate"]["value"] < summ["backstepping"]["not_settled_rate"]["value"]
    assert lines[0].startswith("| law | mean_rho_L2 (veh/km)") and len(lines) == 2 + 3
    with pytest.raises(ValueError, match="told must be one of"):
        LawSpec("x", "x", jt.open_loop, told="alpha")


def test_chunks_ordered_by_delay_give_every_scenario_the_same_values_in_its_own_place():
    """``evaluate_laws`` chunks the scenarios in the order of their delays (a chunk's predictor loop runs its largest
    D): the measures come back in the scenarios' order, bit for bit those of chunks in the drawn order."""
    scen = sample(DIST, "test", 12, seed=3, base=TINY)
    order = delay_order(scen)
    delays = np.asarray(scen.plants.delay)
    assert np.all(np.diff(delays[order]) >= 0) and not np.all(order == np.arange(12))
    laws = [LawSpec("backstepping", "backstepping", lambda: jt.backstepping(4.0), told="delay")]
    got = {b: evaluate_laws(laws, scen, TINY, horizon_s=60.0, chunk=4, log=lambda s: None, by_delay=b)["backstepping"]
           for b in (True, False)}
    for k, v in got[False].items():
        np.testing.assert_array_equal(got[True][k], v, err_msg=k)
    assert np.ptp(got[True]["mean_rho_L2"]) > 0  # distinct scenarios: a permuted result would be caught


def test_tuning_searches_the_train_split_within_bounds_and_never_loses_the_start():
    from jaxtraffic.compare.tuning import tune
    from jaxtraffic.paper.laws import TUNABLE

    scen = sample(DIST, "train", 6, seed=0, base=TINY)
    got = tune(TUNABLE["backstepping"], scen, TINY, horizon_s=60.0, population=4, generations=2,
               log=lambda s: None)
    assert set(got["best"]) == {"k", "keep"} and 0.05 <= got["best"]["k"] <= 3.0 and 0 <= got["best"]["keep"] <= 1
    assert [h["generation"] for h in got["history"]] == [0, 1]
    hist = [h["best_mean_rho_L2"] for h in got["history"]]
    assert hist[1] <= hist[0] and got["fitness"] == -hist[-1]  # the best so far is kept
    assert got["budget"] == {"population": 4, "generations": 2, "scenarios": 6, "horizon_s": 60.0}
    with pytest.raises(ValueError, match="train split"):
        tune(TUNABLE["backstepping"], sample(DIST, "test", 4, base=TINY), TINY, log=lambda s: None)


def test_tuning_under_sensor_noise_scores_each_candidate_as_the_comparison_judges_it():
    """A train split drawn with sensor noise: the tuning's fitness of each candidate is minus the capped mean of
    the comparison's own measure of that law on those scenarios (the same noise levels and keys), and the noise
    matters (the noise-free split scores the candidates differently)."""
    from jaxtraffic.compare import stats
    from jaxtraffic.compare.protocol import steps_of
    from jaxtraffic.compare.tuning import fitness
    from jaxtraffic.paper.laws import TUNABLE

    t = TUNABLE["backstepping"]
    scen = sample(ScenarioDistribution(sensor_noise_range=(0.05, 0.1)), "train", 4, seed=0, base=TINY)
    assert np.all(scen.draws["sensor_noise"] >= 0.05)
    pop = np.array([[1.0, 0.3], [0.5, 0.0]], np.float32)
    n_steps, every = steps_of(60.0, float(TINY.dt))
    got = fitness(t, pop, scen, TINY, n_steps, every)
    for i, (k, keep) in enumerate(pop):
        law = LawSpec("cand", "cand", lambda k=k, keep=keep: t.build(np.float32(4.0), k, keep), told="delay")
        judged = evaluate_laws([law], scen, TINY, horizon_s=60.0, log=lambda s: None, by_delay=False)["cand"]
        np.testing.assert_allclose(got[i], -stats.capped(judged["mean_rho_L2"]).mean(), rtol=1e-5)
    clean = sample(DIST, "train", 4, seed=0, base=TINY)
    np.testing.assert_array_equal(clean.rho0, scen.rho0)  # the same scenarios but for the noise
    assert not np.allclose(fitness(t, pop, clean, TINY, n_steps, every), got, rtol=1e-4)


@pytest.mark.skipif(not __import__("os").path.exists("/proc/self/maps"), reason="needs Linux's /proc/self/maps")
def test_a_long_comparison_releases_its_programs_memory_mappings():
    """Each law's compiled programs hold memory mappings on the CPU backend; ``release`` (the default) drops them
    after each law, so a comparison of many laws in one process stays below the kernel's limit
    (vm.max_map_count): the main job crashed there before."""

    def mappings() -> int:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)

    scen = sample(DIST, "test", 4, seed=0, base=TINY)
    laws = [LawSpec(f"lyapunov{k}", "Lyapunov", lambda k=k: jt.lyapunov(0.5 + 0.1 * k)) for k in range(3)]
    growth = {}
    for release in (False, True):
        jax.clear_caches()
        before = mappings()
        evaluate_laws(laws, scen, TINY, horizon_s=20.0, log=lambda s: None, release=release)
        growth[release] = mappings() - before
    assert growth[False] > 60, growth  # each law compiles its own programs (tens of mappings each)
    assert abs(growth[True]) < 0.25 * growth[False], growth
