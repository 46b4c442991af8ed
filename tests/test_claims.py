"""Claim verdicts, settling times, summaries and Table 2 on hand-made metric dicts (no simulation).

``paper_like_metrics`` is a metrics.json content in which every claim of the paper holds (docs/model.md
section 11, with the paper's own Table 2 values); each test changes a few numbers and checks that the
verdicts move the way the criteria (``claims.CRITERIA``) say they must.
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from jaxtraffic.paper import claims, summaries
from jaxtraffic.paper.scenarios import SETTLE_FRACTION, EvalConfig, Outcome
from jaxtraffic.paper.table2 import table2_rows

CFG = EvalConfig()  # the paper's 1 km road and 300 s: equilibrium J_TTT = 3.2208e7, J_fuel = 8.077e5
CURVE = {"eval_reward": np.array([-5.0, -0.5, -0.05])}


def entry(t_reward=30.0, rho=50.0, v=60.0, effort=0.1, diverged=False, J=(3.2e7, 8.1e5, 1.3e5), **extra):
    """One metrics.json entry (single seed): times in s, None = never."""
    return {"J_TTT": J[0], "J_fuel": J[1], "J_comfort": J[2], "final_rho_L2": 0.1, "final_v_L2": 1e-3,
            "final_reward": -0.01 if t_reward is not None else -3.0, "time_to_reward_-0.1_s": t_reward,
            "diverged": diverged, "control_effort": effort, "t_settle_rho_s": rho, "t_settle_v_s": v,
            "n_seeds": 1, **extra}


def seeded(times, diverged=None):
    """An entry averaged over seeds, with the per-seed times to reward >= -0.1 (None = never)."""
    diverged = diverged or [False] * len(times)
    e = entry(t_reward=None if None in times else float(np.mean(times)), diverged=any(diverged))
    e.update(n_seeds=len(times), per_seed={"diverged": diverged, "time_to_reward_-0.1_s": list(times)})
    return e


OPEN_LOOP = dict(t_reward=None, rho=None, v=None, effort=0.0, J=(3.4e7, 8.6e5, 9.8e5))


@pytest.fixture
def metrics():
    return {
        "delay0": {"open_loop": entry(**OPEN_LOOP),
                   "lyapunov": entry(t_reward=125.0, rho=150.0, v=100.0, effort=0.2),
                   "ppo": entry(t_reward=28.0, rho=50.0, v=150.0, effort=0.1)},
        "delay4": {"open_loop": entry(**OPEN_LOOP),
                   "lyapunov": entry(t_reward=None, rho=None, v=None),
                   "backstepping": entry(t_reward=72.0, rho=100.0, v=90.0, J=(3.2e7, 8.1e5, 1.3e5)),
                   "ppo": entry(t_reward=30.0, rho=60.0, v=120.0, J=(3.2e7, 8.1e5, 1.5e5))},
        "alpha_noise": {"backstepping": seeded([None, None, 90.0]), "ppo": seeded([40.0, 50.0, 60.0])},
        "delay_mismatch_3": {"backstepping": entry(rho=100.0, v=90.0), "ppo": entry(rho=80.0, v=110.0)},
        "delay_mismatch_5": {"backstepping": entry(rho=150.0, v=140.0), "ppo": entry(rho=100.0, v=120.0)},
    }


def claims_of(metrics, curve=CURVE):
    return {c["id"]: c for c in claims.evaluate_claims(metrics, CFG, curve, "the D = 4 s policy")}


def check(claim, text):
    """The one check of ``claim`` whose text contains ``text``; its ``passed``."""
    found = [c for c in claim["checks"] if text in c.text]
    assert len(found) == 1, [c.text for c in claim["checks"]]
    return found[0].passed


# ----------------------------------------------------------------------------- verdict
@pytest.mark.parametrize("passed, expected", [
    ([True, True], "reproduced"),
    ([True, False], "partly"),
    ([False, False], "not reproduced"),
    ([False, None], "not reproduced"),  # a check that cannot be measured does not count
    ([True, None], "reproduced"),
    ([None, None], "not measured"),
    ([], "not measured"),
])
def test_verdict(passed, expected):
    assert claims.verdict([claims.Check("c", "m", p) for p in passed]) == expected


def test_stabilised_single_and_seeded():
    assert claims.stabilised(entry(t_reward=10.0))
    assert not claims.stabilised(entry(t_reward=None))
    assert not claims.stabilised(entry(t_reward=10.0, diverged=True))
    assert claims.stabilised(seeded([1.0, 2.0]))
    assert not claims.stabilised(seeded([1.0, None]))  # every seed must stabilise
    assert not claims.stabilised(seeded([1.0, 2.0], diverged=[False, True]))
    assert claims.stabilised_fraction(seeded([1.0, None, 3.0, None])) == 0.5
    assert claims.stabilised_fraction(seeded([1.0, 2.0], diverged=[True, False])) == 0.5
    assert claims.stabilised_fraction(entry(t_reward=None)) == 0.0


def test_comparison_helpers_ties_and_never():
    assert not claims._less(1.0, 1.0) and not claims._less(0.99, 1.0) and claims._less(0.97, 1.0)  # 2 % margin
    assert claims._faster(10.0, None) and not claims._faster(None, 10.0) and not claims._faster(None, None)
    assert not claims._faster(10.0, 10.0)  # a tie is not a win
    assert claims._comparable(100.0, 150.0) and not claims._comparable(100.0, 151.0)
    assert not claims._comparable(None, 100.0)
    assert claims._conv({"t_settle_rho_s": 3.0, "t_settle_v_s": 5.0}) == 5.0
    assert claims._conv({"t_settle_rho_s": 3.0, "t_settle_v_s": None}) is None


# ----------------------------------------------------------------------------- evaluate_claims
def test_paper_like_metrics_reproduce_every_claim(metrics):
    out = claims_of(metrics)
    assert sorted(out) == [1, 2, 3, 4, 5, 6]
    for cid, c in out.items():
        # claim 4 also has km/h-reading checks (no km/h indices in these dicts) and information-only ones
        failed = [k.text for k in c["checks"] if k.passed is not True
                  and not k.text.startswith(("km/h reading", "information only"))]
        assert not failed, (cid, failed)
        assert c["verdict"] == ("partly" if cid == 4 else "reproduced"), cid
    json.dumps([{**c, "checks": [vars(k) for k in c["checks"]]} for c in out.values()])  # serialisable


def test_ppo_worse_everywhere_is_not_reproduced(metrics):
    """PPO diverges in every seed of the noise scenario and backstepping stabilises: claim 5 fails."""
    metrics["alpha_noise"]["ppo"] = seeded([None, None, None], diverged=[True, True, True])
    metrics["alpha_noise"]["backstepping"] = seeded([80.0, 90.0, 95.0])
    assert claims_of(metrics)[5]["verdict"] == "not reproduced"


def test_backstepping_half_the_seeds_is_not_a_failure(metrics):
    metrics["alpha_noise"]["backstepping"] = seeded([None, 90.0])  # fails in 1 of 2: not "fewer than half"
    c5 = claims_of(metrics)[5]
    assert check(c5, "backstepping fails") is False and c5["verdict"] == "partly"


def test_ppo_diverging_at_delay4(metrics):
    metrics["delay4"]["ppo"] = entry(t_reward=None, rho=None, v=None, diverged=True, J=(3.5e7, 8.8e5, 5e5))
    out = claims_of(metrics)
    c1, c3, c4 = out[1], out[3], out[4]
    assert check(c1, "PPO (D = 4 s) reward converges") is False
    assert check(c1, "almost coincide") is False
    assert check(c3, "PPO stabilises at D = 4 s") is False
    assert check(c3, "comparable") is False and check(c3, "density faster") is False
    assert check(c3, "Lyapunov fails") is True and check(c3, "backstepping stabilises") is True
    assert c1["verdict"] == c3["verdict"] == "partly"
    assert check(c4, "ppo J_TTT within") is False  # 8.7 % off the equilibrium
    assert check(c4, "open loop worse") is False
    assert c4["verdict"] == "partly"


def test_delay4_lyapunov_that_stabilises_fails_its_check(metrics):
    metrics["delay4"]["lyapunov"] = entry(t_reward=100.0)
    assert check(claims_of(metrics)[3], "Lyapunov fails") is False


def test_claim2_ties_and_effort(metrics):
    d0 = metrics["delay0"]
    d0["ppo"]["t_settle_rho_s"] = d0["lyapunov"]["t_settle_rho_s"]  # identical: not faster
    d0["ppo"]["control_effort"] = d0["lyapunov"]["control_effort"]
    d0["ppo"]["t_settle_v_s"] = 2.5 * d0["lyapunov"]["t_settle_v_s"]  # slower, but not "a little"
    c2 = claims_of(metrics)[2]
    assert check(c2, "rho faster") is False and check(c2, "less control effort") is False
    assert check(c2, "a little slower") is False
    assert check(c2, "Lyapunov stabilises") is True and c2["verdict"] == "partly"


def test_claim2_ppo_never_settles_v(metrics):
    metrics["delay0"]["ppo"]["t_settle_v_s"] = None
    assert check(claims_of(metrics)[2], "a little slower") is False


def test_claim4_table2_values_and_comfort(metrics):
    d4 = metrics["delay4"]
    d4["ppo"]["J_comfort"] = 1.0e5  # more comfortable than backstepping (the paper has it slightly less)
    d4["open_loop"]["J_TTT"] = 3.5e7
    c4 = claims_of(metrics)[4]
    assert check(c4, "slightly less comfortable") is False
    assert check(c4, "SI reading: values round to the paper") is False
    assert check(c4, "open loop worse") is True
    d4["open_loop"]["J_fuel"] = 8.0e5  # the open loop better than both on J_fuel
    assert check(claims_of(metrics)[4], "open loop worse") is False


def test_claim4_improvements_outside_the_tolerance(metrics):
    metrics["delay4"]["ppo"]["J_comfort"] = 7e5  # 28.6 % improvement vs the paper's 84.3 %
    c4 = claims_of(metrics)[4]
    assert check(c4, "SI reading: improvements over the open loop") is False
    assert check(c4, "slightly less comfortable") is True


def test_claim4_equilibrium_tolerance(metrics):
    eq = summaries.equilibrium_indices(CFG)
    assert eq["J_TTT"] == pytest.approx(3.2208e7, rel=1e-4) and eq["J_fuel"] == pytest.approx(8.077e5, rel=1e-3)
    metrics["delay4"]["backstepping"]["J_TTT"] = eq["J_TTT"] * 1.031
    metrics["delay4"]["ppo"]["J_fuel"] = eq["J_fuel"] * 0.975
    c4 = claims_of(metrics)[4]
    assert check(c4, "backstepping J_TTT within") is False
    assert check(c4, "ppo J_fuel within") is True


def test_claim6_mismatch(metrics):
    metrics["delay_mismatch_5"]["ppo"] = entry(rho=100.0, v=200.0)  # conv 200 s > backstepping's 150 s
    metrics["delay_mismatch_3"]["backstepping"] = entry(t_reward=None, rho=None, v=None)
    c6 = claims_of(metrics)[6]
    assert check(c6, "D = 5 s: PPO converges slightly better") is False
    assert check(c6, "backstepping stabilises with plant D = 3 s") is False
    assert check(c6, "D = 3 s: similar convergence") is False
    assert check(c6, "ppo stabilises with plant D = 5 s") is True
    assert c6["verdict"] == "partly"


def test_learning_curve_missing_or_short_of_the_rule(metrics):
    c1 = claims_of(metrics, curve=None)[1]
    assert check(c1, "training reaches the stop rule") is None and c1["verdict"] == "reproduced"
    c1 = claims_of(metrics, curve={"eval_reward": np.array([-3.0, -0.2, np.nan])})[1]
    assert check(c1, "training reaches the stop rule") is False and c1["verdict"] == "partly"
    c1 = claims_of(metrics, curve={"eval_reward": np.array([np.nan])})[1]
    assert check(c1, "training reaches the stop rule") is None
    # a population: its best member met the rule although the members' mean did not
    pop = {"eval_reward": np.array([-3.0, -0.4]), "eval_reward_max": np.array([-2.0, -1e-4])}
    assert check(claims_of(metrics, curve=pop)[1], "training reaches the stop rule") is True
    pop["eval_reward_max"] = np.array([np.nan, np.nan])  # a curve without the column's values: the mean
    assert check(claims_of(metrics, curve=pop)[1], "training reaches the stop rule") is False


def test_coinciding_reward_curves_tolerance(metrics):
    metrics["delay0"]["ppo"]["time_to_reward_-0.1_s"] = 41.0  # 30 s vs 41 s: > max(10 s, 25 % of 30 s)
    assert check(claims_of(metrics)[1], "almost coincide") is False
    metrics["delay0"]["ppo"]["time_to_reward_-0.1_s"] = 39.0
    assert check(claims_of(metrics)[1], "almost coincide") is True


# ----------------------------------------------------------------------------- settling times
T = np.array([0.0, 10.0, 20.0, 30.0, 40.0])


@pytest.mark.parametrize("y, expected", [
    ([5.0, 3.0, 0.5, 0.4, 0.3], 20.0),  # below the threshold from t = 20 s on
    ([0.5, 0.4, 0.3, 0.2, 0.1], 0.0),  # always below: settled from the start
    ([5.0, 0.5, 3.0, 0.5, 0.5], 30.0),  # dips below, comes back: the last crossing counts
    ([5.0, 0.5, 0.5, 0.5, 3.0], None),  # ends above: never settles
    ([5.0, 0.5, 1.0, 0.5, 0.5], 10.0),  # == threshold counts as below
    ([5.0, 0.5, np.nan, 0.5, 0.5], 30.0),  # NaN is not below
    ([5.0, 0.5, 0.5, 0.5, np.nan], None),
])
def test_settle_time(y, expected):
    assert summaries._settle_time(T, np.asarray(y), 1.0) == expected


def _outcome(rho_l2, v_l2, **metric_overrides):
    """An Outcome of len(rho_l2) seeds on the time grid T (only what ``summarise`` reads is filled)."""
    rho_l2, v_l2 = np.atleast_2d(rho_l2).astype(float), np.atleast_2d(v_l2).astype(float)
    n = rho_l2.shape[0]
    m = {"J_TTT": np.full(n, 3.2e7), "J_fuel": np.full(n, 8.1e5), "J_comfort": np.arange(1.0, n + 1) * 1e3,
         "final_rho_L2": rho_l2[:, -1], "final_v_L2": v_l2[:, -1], "final_reward": np.full(n, -0.01),
         "time_to_reward_target_s": np.full(n, 15.0), "diverged": np.zeros(n, bool),
         "diverged_at_s": np.full(n, np.inf), "control_effort": np.full(n, 0.1)}
    m.update({k: np.asarray(v) for k, v in metric_overrides.items()})
    empty = np.zeros((n, len(T), 1))
    return Outcome(metrics=m, t=T, rho=empty, v=empty, h=empty, reward=np.zeros((n, len(T))), rho_L2=rho_l2,
                   v_L2=v_l2)


INIT = (10.0, 1.0)  # initial L2 norms: settling thresholds SETTLE_FRACTION x these


def test_summarise_single_run():
    assert SETTLE_FRACTION == 0.1
    out = _outcome([10.0, 5.0, 0.9, 0.5, 0.2], [1.0, 0.05, 0.2, 0.05, 0.01],
                   time_to_reward_target_s=[np.inf])
    e = summaries.summarise(out, INIT)
    assert e["t_settle_rho_s"] == 20.0 and e["t_settle_v_s"] == 30.0
    assert e["time_to_reward_-0.1_s"] is None  # inf (never) becomes null
    assert e["diverged"] is False and e["diverged_at_s"] is None and e["n_seeds"] == 1
    assert "per_seed" not in e and "std" not in e
    assert set(summaries.REQUIRED_KEYS) <= set(e)
    assert e["final_rho_L2"] == 0.2 and e["J_comfort"] == 1e3
    json.dumps(e, allow_nan=False)


def test_summarise_seeds_means_and_a_diverged_seed():
    rho = [[10.0, 0.5, 0.5, 0.5, 0.5], [10.0, 5.0, 0.5, 0.5, 0.5], [10.0, 5.0, 5.0, 5.0, 5.0]]
    v = [[1.0, 0.05, 0.05, 0.05, 0.05]] * 3
    out = _outcome(rho, v, time_to_reward_target_s=[10.0, 20.0, 30.0])
    e = summaries.summarise(out, INIT)
    assert e["n_seeds"] == 3 and e["t_settle_rho_s"] is None  # one seed never settles: no mean time
    assert e["t_settle_v_s"] == 10.0 and e["time_to_reward_-0.1_s"] == 20.0
    assert e["per_seed"]["t_settle_rho_s"] == [10.0, 20.0, None]
    assert e["J_comfort"] == 2e3 and e["std"]["J_comfort"] == pytest.approx(np.std([1e3, 2e3, 3e3]))
    assert e["diverged_fraction"] == 0.0

    div = _outcome(rho[:2], v[:2], diverged=[False, True], diverged_at_s=[np.inf, 42.0],
                   time_to_reward_target_s=[10.0, 20.0])
    e = summaries.summarise(div, INIT)
    assert e["diverged"] is True and e["diverged_at_s"] == 42.0 and e["diverged_fraction"] == 0.5
    assert e["per_seed"]["t_settle_rho_s"] == [10.0, None]  # a diverged seed never settles
    assert e["per_seed"]["diverged"] == [False, True] and e["t_settle_rho_s"] is None
    assert not claims.stabilised(e) and claims.stabilised_fraction(e) == 0.5  # the claims read the summaries
    json.dumps(e, allow_nan=False)


# ----------------------------------------------------------------------------- Table 2
@pytest.mark.parametrize("ol, c, expected", [
    (10.0, 8.0, 20.0), (10.0, 12.0, -20.0), (10.0, 10.0, 0.0), (0.0, 1.0, None), (None, 1.0, None),
    (1.0, None, None),
])
def test_improvement(ol, c, expected):
    assert summaries.improvement(ol, c) == (None if expected is None else pytest.approx(expected))


def test_table2_rows(metrics):
    rows = {(r["index"], r["controller"]): r for r in table2_rows(metrics, CFG)}
    assert {i for i, _ in rows} == set(summaries.INDICES)
    tt, com = rows[("J_TTT", "ppo")], rows[("J_comfort", "ppo")]
    assert tt["equilibrium_SI"] == pytest.approx(3.2208e7, rel=1e-4) and com["equilibrium_SI"] is None
    assert rows[("J_TTT", "open_loop")]["ours_SI"] == 3.4e7 and rows[("J_TTT", "open_loop")]["paper"] == 3.4e7
    assert tt["improvement_pct_SI"] == pytest.approx(100 * (3.4 - 3.2) / 3.4)
    assert tt["improvement_pct_paper"] == 5.97
    bs = rows[("J_comfort", "backstepping")]
    assert bs["improvement_pct_SI"] == pytest.approx(100 * (9.8 - 1.3) / 9.8)
    assert com["paper"] == 1.5e5 and com["improvement_pct_paper"] == 84.3
    assert "improvement_pct_si" not in rows[("J_TTT", "open_loop")]


def test_table2_rows_with_a_missing_controller(metrics):
    m = copy.deepcopy(metrics)
    del m["delay4"]["ppo"]
    rows = {(r["index"], r["controller"]): r for r in table2_rows(m, CFG)}
    assert rows[("J_fuel", "ppo")]["ours_SI"] is None and rows[("J_fuel", "ppo")]["improvement_pct_SI"] is None
    assert rows[("J_fuel", "backstepping")]["ours_SI"] == 8.1e5
    assert math.isclose(rows[("J_fuel", "backstepping")]["improvement_pct_SI"], 100 * (8.6 - 8.1) / 8.6)
