"""Issue 49, item 4: every density quantity a user reads is in veh/km (the state stays in veh/m, SI); files of an
earlier version, which held them in veh/m, are read (the gain oracle) or compared (compare_results.py) in veh/km."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraffic as jt
from jaxtraffic.paper.oracle import load_oracle
from jaxtraffic.paper.scenarios import EvalConfig, initial_norms
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import STABLE_STD, VEH_PER_KM, density_l2, density_std

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from compare_results import differences, upgrade  # noqa: E402

P = jt.TrafficParams(n_points=21, delay=1.0)


def test_the_density_metrics_are_in_veh_per_km_and_the_state_in_veh_per_m():
    res = jt.simulate(P, jt.backstepping(delay=1.0), n_steps=200, record=jt.Record(every=50),
                      metrics=("final_rho_L2", "late_max_rho_std", "J_TTT", "diverged"))
    rho_bar = float(jt.equilibrium(P)[0])
    assert 0.05 < rho_bar < 0.2  # veh/m: the state's unit
    final = np.asarray(res.final.rho, float)
    l2_km = 1e3 * np.sqrt(np.mean((final - rho_bar) ** 2))
    assert float(res.metrics["final_rho_L2"]) == pytest.approx(l2_km, rel=1e-5)
    rho0, _ = paper_initial_condition(P)
    l2_0 = 1e3 * np.sqrt(np.mean((np.asarray(rho0, float) - rho_bar) ** 2))
    assert l2_0 == pytest.approx(10.0 / np.sqrt(2), rel=0.05)  # the paper's 10 veh/km cosine: ~7.07 veh/km
    assert float(res.trajectory.rho_L2[0]) == pytest.approx(l2_0, rel=1e-5)
    assert float(res.metrics["late_max_rho_std"]) >= 1e3 * np.std(final) * (1 - 1e-6)
    # J_TTT integrates rho in veh/km: the same factor as the norms (1000 x veh/m)
    assert float(res.metrics["J_TTT"]) == pytest.approx(VEH_PER_KM * rho_bar * P.L * 200 * P.dt, rel=0.02)
    assert float(density_l2(jnp.asarray(final), rho_bar)) == pytest.approx(l2_km, rel=1e-5)
    assert float(density_std(jnp.asarray(final))) == pytest.approx(1e3 * np.std(final), rel=1e-5)
    assert STABLE_STD == 0.5  # veh/km
    assert initial_norms(EvalConfig(n_points=21))[0] == pytest.approx(l2_0, rel=1e-5)


def test_an_oracle_file_of_an_earlier_version_loads_in_veh_per_km(tmp_path):
    cfg = EvalConfig(robust_delays=(0.0, 4.0), robust_alphas=(0.15,), robust_horizon_s=12.0)
    rows = {"per_cell": {"diverged": [[False], [True]], "final_rho_spatial_std": [[2e-4], [1e-2]], "gains": None}}
    old = {"delays_s": [0.0, 4.0], "alphas": [0.15], "horizon_s": 12.0, "stable_std_veh_m": 0.5e-3, "rows": rows}
    (tmp_path / "old.json").write_text(json.dumps(old))
    got = load_oracle(tmp_path / "old.json", cfg)
    np.testing.assert_allclose(got["per_cell"]["final_rho_spatial_std"], [[0.2], [10.0]])
    new = {**{k: v for k, v in old.items() if k != "stable_std_veh_m"}, "stable_std_veh_per_km": STABLE_STD}
    (tmp_path / "new.json").write_text(json.dumps(new))
    np.testing.assert_allclose(load_oracle(tmp_path / "new.json", cfg)["per_cell"]["final_rho_spatial_std"],
                               [[2e-4], [1e-2]])


def test_compare_results_reads_an_older_tree_in_veh_per_km():
    old = {"units": {"final_rho_L2": "veh/m", "J_TTT": "veh/km·m·s"},
           "controllers": {"a": {"final_rho_L2": [[1e-3, None]], "final_rho_offset": [[-2e-4]], "diverged": [[0]]}},
           "meta": {"nominal": {"rho_bar_veh_per_m": 0.1}, "initial_L2": {"rho_veh_per_m": 0.007}},
           "labels": ["D=3 amp=0.01 k=4 phase=0.00"], "J_TTT": 3.0e7}
    new = {"units": {"final_rho_L2": "veh/km", "J_TTT": "veh/km·m·s"},
           "controllers": {"a": {"final_rho_L2": [[1.0, None]], "final_rho_offset": [[-0.2]], "diverged": [[0]]}},
           "meta": {"nominal": {"rho_bar_veh_per_km": 100.0}, "initial_L2": {"rho_veh_per_km": 7.0}},
           "labels": ["D=3 amp=10 veh/km k=4 phase=0.00"], "J_TTT": 3.0e7}
    assert differences(upgrade(old), new, rtol=1e-12) == []
    assert len(differences(old, new)) > 5  # without the conversion every density differs
    assert differences(upgrade(new), new) != []  # a new tree is not to be converted again
