"""End to end: evaluate.py on the tiny trained policy, a tiny grid and a short horizon; check outputs.

The policies are run ``A`` of the suite's one tiny training session (``tiny_runs.py``, fixture
``tiny_run_a`` in ``conftest.py``), which ``test_train.py`` checks in detail, and the tiny
gradient-trained run that the same session writes next to it.
"""

from __future__ import annotations

import json
import math

import pytest
from tiny_runs import GRADIENT_ROOT, REPO

import evaluate
from jaxtraffic.paper import REQUIRED_KEYS, SCENARIOS


@pytest.fixture(scope="module")
def tiny_run(tiny_run_a):
    return tiny_run_a


def _walk_numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _walk_numbers(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _walk_numbers(v)
    elif isinstance(obj, float):
        yield obj


@pytest.mark.slow
def test_evaluate_end_to_end(tiny_run, tmp_path, monkeypatch):
    from jaxtraffic.paper import fair

    monkeypatch.setattr(fair, "HORIZON_S", 20.0)  # the held-out comparison's horizon (600 s in the main job)
    out = tmp_path / "results"
    # the tiny gradient-trained gains run is where evaluate.py looks for it (the other gradient runs are absent)
    runs_root = tiny_run.parent / GRADIENT_ROOT
    assert (runs_root / "gradient-gains" / "config.json").is_file()
    # oracle rows of the paper plant's map (3 triples), which the evaluation draws and tabulates
    from jaxtraffic.paper.oracle import gain_grid_map, oracle_json, oracle_rows
    from jaxtraffic.paper.scenarios import EvalConfig, robust_axis

    map_cfg = EvalConfig(n_points=21, robust_delays=robust_axis(2, 0.0, 8.0, 0.1),
                         robust_alphas=robust_axis(2, 0.05, 0.6), robust_horizon_s=12.0, numerics_check=False)
    triples = [(0.0, -1.0, -1.5), (0.0, 0.0, -2.0), (0.0, -0.5, -1.0)]
    rows = oracle_rows(triples, *gain_grid_map(map_cfg, triples, log=lambda _: None))
    (tmp_path / "oracle").mkdir()
    (tmp_path / "oracle" / "paper.json").write_text(json.dumps(oracle_json(map_cfg, triples, rows, 25.0)))
    metrics = evaluate.main(["--run", str(tiny_run), "--out", str(out), "--horizon", "6", "--noise-seeds", "2",
                             "--robust-grid", "2x2", "--gradient", "existing", "--runs-root", str(runs_root),
                             "--reference-grid", "41x1", "--reference-robust-grid", "2x1",
                             "--oracle-dir", str(tmp_path / "oracle"), "--fair", "3", "--fair-other", "2",
                             "--controller", f"ppo_predict={REPO / 'tests' / 'external_controller.py'}:"
                             f"predict_controller:{tiny_run}"])
    on_disk = json.loads((out / "metrics.json").read_text())
    assert "units" in on_disk and "meta" in on_disk
    skipped = {"grad_network"}  # (grad_gains, grad_robust and grad_residual are there)
    # --controller ppo_predict (the PPO run as a plain predict(obs), bridged back): wherever PPO is
    expected = {s.name: set(s.controllers) - skipped | ({"ppo_predict"} if "ppo" in s.controllers else set())
                for s in SCENARIOS}
    assert "grad_gains" in expected["delay4"]
    assert set(expected) == {"delay0", "delay4", "alpha_noise", "alpha_noise_held_1s", "alpha_noise_held_10s",
                             "alpha_noise_node_held_10s", "alpha_noise_model_sees", "delay_mismatch_3",
                             "delay_mismatch_5"}
    for scenario, controllers in expected.items():
        assert set(on_disk[scenario]) == controllers, scenario
        for name in controllers:
            entry = on_disk[scenario][name]
            for key in REQUIRED_KEYS:
                assert key in entry, (scenario, name, key)
            for key in ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward"):
                assert isinstance(entry[key], float) and math.isfinite(entry[key]), (scenario, name, key)
            assert isinstance(entry["diverged"], bool)
            t = entry["time_to_reward_-0.1_s"]
            assert t is None or (isinstance(t, float) and 0 <= t <= 6.0)
    assert all(math.isfinite(x) for x in _walk_numbers(on_disk))  # JSON holds no NaN/inf
    # the held-out comparison (issue 47, item 8): every registered law and the user's on 3 test scenarios
    held = json.loads((out / "fair" / "paper.json").read_text())
    assert {"open_loop", "backstepping", "backstepping_f25", "adaptive_backstepping", "ppo", "grad_residual",
            "ppo_predict"} <= set(held["laws"]) and held["scenarios"]["n"] == 3 and held["scenarios"]["split"] == "test"
    # ... and on the other plant (--fair-other), each plant's table a section of the first plant's REPORT.md
    other = json.loads((out / "fair" / "reference.json").read_text())
    assert set(other["laws"]) == set(held["laws"]) and other["scenarios"]["n"] == 2
    assert all(f"## Held-out comparison (the test split, {p} plant)" in (out / "REPORT.md").read_text()
               for p in ("paper", "reference"))
    assert set(metrics) >= set(expected)
    for name in ("table2.md", "table2.csv", "REPORT.md", "fig3a_learning_curve.png", "fig3b_reward.png",
                 "fig5_spacetime_delay4.png", "fig6_l2_delay4.png", "robustness_map.png"):
        assert (out / name).stat().st_size > 0, name
    table = (out / "table2.csv").read_text()
    assert "J_TTT" in table and "paper" in table.lower()
    report = (out / "REPORT.md").read_text()
    assert "Beyond the paper: PPO and gradient-based training" in report
    assert "gradient: 3 constant gains" in report and "gradient-gains" in report
    # the robust delay schedule: on the map (told each cell's delay) with the offset from the plant's own
    # equilibrium, in the scenarios, and the oracle rows on the paper plant only (the reference map differs)
    assert "gradient: delay schedule (robust)" in report and "grad_robust" in on_disk["delay4"]
    robust = json.loads((out / "robustness.json").read_text())["controllers"]
    assert {"grad_robust", "backstepping"} <= set(robust) and "final_rho_offset" in robust["grad_robust"]
    # the learned residual on adaptive backstepping: told D on the map, like the schedule
    assert "grad_residual" in on_disk["delay4"] and "learned residual on adaptive backstepping" in report
    told = json.loads((out / "robustness.json").read_text())["table"]["rows"]
    assert "grad_residual" in robust and told["grad_residual"]["told"] == "D"
    assert "oracle: gains by delay" in report
    assert "oracle: gains by delay" not in (out / "reference" / "REPORT.md").read_text()
    # both readings with units, the numerical check beside Table 2, claim 5 per reading
    assert "J_fuel_kmh" in on_disk["units"] and "J_comfort_kmh" in on_disk["delay4"]["open_loop"]
    rel = on_disk["numerics"]["rel_diff"]
    assert set(rel) == {"refined", "scheme"} and "J_comfort" in rel["refined"]["backstepping"]
    assert "Delta refined" in (out / "table2.md").read_text()
    claims = json.loads((out / "claims.json").read_text())
    c5 = next(c for c in claims if c["id"] == 5)
    assert set(c5["readings"]) == {s.name for s in SCENARIOS if s.seeded}
    assert on_disk["meta"]["fig7_reading"] in c5["readings"]
    assert "Numerical uncertainty" in report and "alpha_noise_model_sees" in report
    # the same experiments on the reference plant (here 41 points, MUSCL), claim by claim side by side
    ref = json.loads((out / "reference" / "metrics.json").read_text())
    assert ref["meta"]["grid"]["n_points"] == 41 and ref["meta"]["grid"]["scheme"] == "muscl"
    assert set(ref["delay4"]) == expected["delay4"]
    plants = json.loads((out / "plants.json").read_text())
    assert set(plants["claims"]) == {"paper", "reference"} and set(plants["claims"]["reference"]) == set("123456")
    assert "The experiments on the reference plant" in report and (out / "fig_plants_delay4.png").stat().st_size
    assert "rho L2 6 s (veh/km), paper" in report and "D = 4 s, 6 s, backstepping" in report  # --horizon 6, as run
    # the controller brought in: the PPO run bridged through predict(obs) scores as the run itself, on both
    # plants, and stands in REPORT.md's tables (the map, the numerical check, the learned controllers' section)
    for m in (on_disk, ref):
        for scenario in ("delay4", "delay_mismatch_5", "alpha_noise"):
            for key in ("J_comfort", "final_rho_L2"):
                assert m[scenario]["ppo_predict"][key] == pytest.approx(m[scenario]["ppo"][key], rel=1e-3, abs=1e-8)
    assert "ppo_predict" in robust and "ppo_predict" in rel["refined"] and "| ppo_predict |" in report
    # the evaluated controllers themselves, loadable from the results
    from jaxtraffic.runs import load_policy

    assert {p.name for p in (out / "runs").iterdir()} == {"ppo", "grad_gains", "grad_robust", "grad_residual"}
    load_policy(out / "runs" / "grad_residual")
    load_policy(out / "runs" / "ppo")
    load_policy(out / "runs" / "grad_gains")
    # every learned run's certificate, in its summary and in the report
    assert "Stability certificate of the learned laws" in report and (out / "fig_certificate.png").stat().st_size
    # the residual's law is not what the certificate models: listed with the reason, not certified
    assert "learned residual on adaptive backstepping: no certificate: control.stability certifies" in report


def test_figures_drawn_in_the_background_report_their_lines_and_errors_in_the_caller():
    """``driver._Background``: the thread's log lines come out at ``join``, and so does its exception."""
    from jaxtraffic.paper.driver import _Background

    def draw(log):
        log("  wrote a.png")
        raise RuntimeError("bad figure")

    lines: list[str] = []
    with pytest.raises(RuntimeError, match="bad figure"):
        _Background(draw).join(lines.append)
    assert lines == ["  wrote a.png"]
    assert _Background(lambda log: ["b.png"]).join(lines.append) == ["b.png"]
