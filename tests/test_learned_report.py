"""REPORT.md's comparison of the learned controllers (``paper.learned``) on hand-made inputs."""

from __future__ import annotations

import numpy as np

from jaxtraffic.paper.learned import comparison_section, seconds_to_beat, stabilised_cells


def test_stabilised_cells_count_calm_non_diverged_cells():
    r = {"diverged": np.array([[False, True], [False, False]]),
         "final_rho_spatial_std": np.array([[0.1, 0.01], [0.6, 0.49]])}  # veh/km
    assert stabilised_cells(r) == 2  # the diverged calm cell and the 0.6 veh/km cell do not count


def test_seconds_to_beat_needs_both_l2_and_comfort():
    curve = {"wall_s": np.array([1.0, 2.0, 3.0]), "eval_rho_L2": np.array([0.2, 0.5, 0.2]),
             "eval_J_comfort": np.array([5000.0, 100.0, 100.0])}
    assert seconds_to_beat(curve, rho_l2=0.3, j_comfort=4000.0) == 3.0
    assert seconds_to_beat(curve, rho_l2=0.1, j_comfort=4000.0) is None
    assert seconds_to_beat(None, 1.0, 1.0) is None


def test_comparison_section_reports_each_run_and_the_map():
    metrics = {"delay4": {"backstepping": {"final_rho_L2": 0.34, "J_comfort": 4000.0},  # veh/km
                          "grad_gains": {"final_rho_L2": 0.1, "J_comfort": 2000.0}}}
    alphas, delays = (0.1, 0.15), (0.0, 4.0)
    calm = {"diverged": np.zeros((2, 2), bool), "final_rho_spatial_std": np.array([[1e3, 0.01], [1e3, 0.01]])}
    rough = {"diverged": np.array([[True, False], [True, False]]),
             "final_rho_spatial_std": np.array([[1e3, 0.01], [1e3, 1e3]])}
    runs = {"grad_gains": {"run_dir": "runs/g", "summary": {"wall_s": 12.5, "env_steps": 9e5},
                           "curve": {"wall_s": np.array([9.0]), "eval_rho_L2": np.array([0.1]),
                                     "eval_J_comfort": np.array([2000.0])}}}
    lines = comparison_section(metrics, runs, {"grad_gains": calm, "backstepping": rough}, alphas, delays, 20.0)
    text = "\n".join(lines)
    assert "D = 4 s, 20 s, backstepping" in text and "300 s" not in text  # the evaluation's horizon, as run
    row = next(line for line in lines if line.startswith("| gradient: 3 constant gains"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[2:5] == ["12.5", "9e+05", "9.0"]
    assert cells[5:8] == ["0.100", "2000", "0.50"]
    assert cells[8:] == ["2/4", "0-4"]
    assert any(line.startswith("| backstepping") and "| 1/4 |" in line for line in lines)
    assert comparison_section(metrics, {}, {}, alphas, delays, 300.0) == []
