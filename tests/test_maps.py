"""The robustness map judged by what each controller is told (paper.maps, issue 38): the new rows, the
exclusion of the cells inconsistent before any control acts, and the adaptive row against a direct rollout."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SMALL

from jaxtraffic.control import adaptive_backstepping, backstepping, open_loop
from jaxtraffic.paper.maps import (
    best_learned,
    excluded_cells,
    excluded_text,
    four_rows,
    map_controllers,
    map_table,
    rejudge,
    table_lines,
)
from jaxtraffic.paper.numerics import deploy
from jaxtraffic.paper.plants import _map_lines
from jaxtraffic.paper.report import robustness_summary
from jaxtraffic.paper.scenarios import EvalConfig, others, run_batch, run_robustness, told

DELAYS, ALPHAS = (0.0, 4.0), (0.15, 0.6)


def _cfg(horizon: float = 20.0) -> EvalConfig:
    return EvalConfig(n_points=SMALL["n_points"], dt=SMALL["dt"], horizon_s=horizon, robust_horizon_s=horizon,
                      robust_delays=DELAYS, robust_alphas=ALPHAS, numerics_check=False)


@pytest.fixture(scope="module")
def tiny_map():
    cfg = _cfg()
    ctrls = deploy({"open_loop": open_loop(), "backstepping": backstepping(4.0), **map_controllers()}, {}, cfg)
    robust = run_robustness(ctrls, cfg, log=lambda _: None)
    return cfg, ctrls, robust, map_table(robust, {n: told(n, c) for n, c in ctrls.items()}, cfg)


def test_new_rows_with_what_each_is_told(tiny_map):
    cfg, _, robust, table = tiny_map
    assert list(robust) == ["open_loop", "backstepping", "adaptive_backstepping", "backstepping_alpha"]
    assert {n: r["told"] for n, r in table["rows"].items()} == {
        "open_loop": "nothing", "backstepping": "D", "adaptive_backstepping": "D", "backstepping_alpha": "D, alpha"}
    assert table["rows"]["backstepping_alpha"]["role"] == "information bound"
    assert robust["open_loop"]["diverged_step"].shape == (len(DELAYS), len(ALPHAS))
    lines = table_lines(table)
    assert lines[0].startswith("| controller | told |")
    assert any("information bound" in ln and "| D, alpha |" in ln for ln in lines)
    report = "\n".join(robustness_summary(robust, cfg, table=table))
    assert "| backstepping told alpha (information bound) | D, alpha |" in report
    assert "Claim 5 (robustness) re-judged" in report and "not measurable" in report  # no learned law here
    # the map-only rows are not "others" (they do not join the scenarios as a user's controller would)
    assert others(robust) == ()


def test_adaptive_row_equals_a_direct_rollout(tiny_map):
    cfg, _, robust, _ = tiny_map
    nom = cfg.nominal()
    for i, d in enumerate(DELAYS):
        for j, a in enumerate(ALPHAS):
            env = [nom.replace(delay=d, alpha=a)]
            for name, ctrl in (("adaptive_backstepping", adaptive_backstepping(d)),
                               ("backstepping_alpha", adaptive_backstepping(d, adapt=False, alpha0=a))):
                res = run_batch(deploy({name: ctrl}, {}, cfg)[name], env, [0], cfg, record=False)
                for k in ("final_rho_L2", "final_v_L2", "diverged"):
                    np.testing.assert_allclose(np.asarray(res.metrics[k], float)[0],
                                               np.asarray(robust[name][k], float)[i, j], rtol=1e-4, atol=1e-8,
                                               err_msg=f"{name} {k} at D {d}, alpha {a}")
    # told alpha is not the adaptive law: the two rows differ where the plant's alpha is not the nominal's
    assert not np.allclose(robust["backstepping_alpha"]["final_rho_L2"][:, 1],
                           robust["adaptive_backstepping"]["final_rho_L2"][:, 1])


def _row(diverged, std, step=None) -> dict[str, np.ndarray]:
    r = {"diverged": np.asarray(diverged, bool), "final_rho_spatial_std": np.asarray(std, float)}
    if step is not None:
        r["diverged_step"] = np.asarray(step)
    return r


def test_a_cell_that_blows_up_before_the_delay_is_excluded():
    cfg = EvalConfig(dt=0.1, robust_delays=DELAYS, robust_alphas=ALPHAS)
    # open loop: (4 s, 0.6) blows up at step 30 = 3 s < D = 4 s: excluded; (0 s, 0.6) at step 30 > D = 0 and
    # (4 s, 0.15) at step 50 = 5 s > 4 s: counted (control acted first)
    robust = {"open_loop": _row([[False, True], [True, True]], [[1e-2, 0.0], [0.0, 0.0]], [[-1, 30], [50, 30]]),
              "adaptive_backstepping": _row([[False, True], [False, True]], [[1e-5, 0.0], [1e-5, 0.0]])}
    ex = excluded_cells(robust, cfg)
    assert ex.tolist() == [[False, False], [False, True]]
    table = map_table(robust, {"open_loop": "nothing", "adaptive_backstepping": "D"}, cfg)
    assert table["controllable"] == 3 and table["cells"] == 4
    assert table["excluded"] == [{"delay_s": 4.0, "alpha": 0.6, "open_loop_diverged_at_s": 3.0}]
    assert table["rows"]["adaptive_backstepping"] == {"told": "D", "role": table["rows"]["adaptive_backstepping"][
        "role"], "stabilised": 2, "diverged": 1, "stabilised_all": 2, "diverged_all": 2}
    assert table["rows"]["open_loop"]["diverged"] == 2 and table["rows"]["open_loop"]["diverged_all"] == 3
    assert "(D 4 s, alpha 0.6) at t = 3.0 s" in excluded_text(table) and "1 of 4 cells excluded" in excluded_text(table)
    # without an open-loop row nothing can be judged inconsistent: every cell counts
    assert not excluded_cells({"backstepping": robust["adaptive_backstepping"]}, cfg).any()


def _table(**rows: tuple[int, int, str]) -> dict:
    return {"cells": 10, "controllable": 10, "excluded": [], "excluded_mask": [[False] * 5] * 2,
            "rows": {n: {"told": t, "role": "", "stabilised": s, "diverged": d, "stabilised_all": s,
                         "diverged_all": d} for n, (s, d, t) in rows.items()}}


def test_claim_5_rejudged_by_what_each_is_told():
    base = {"backstepping": (4, 2, "D"), "adaptive_backstepping": (7, 1, "D"), "backstepping_alpha": (9, 1, "D, alpha")}
    t = _table(**base, ppo=(3, 3, "nothing"), grad_robust=(8, 1, "D"))
    assert best_learned(t) == "grad_robust"
    assert four_rows(t) == ["backstepping", "adaptive_backstepping", "grad_robust", "backstepping_alpha"]
    assert rejudge(t)["verdict"] == "reproduced"
    assert rejudge(_table(**base, grad_robust=(6, 1, "D")))["verdict"] == "reproduced against backstepping only"
    assert rejudge(_table(**base, grad_robust=(4, 1, "D")))["verdict"] == "not reproduced"  # not more than BS
    assert rejudge(_table(**base))["verdict"] == "not measurable"


def test_plants_map_lines_carry_told_and_controllable_counts():
    t = _table(backstepping=(4, 2, "D"), adaptive_backstepping=(7, 1, "D"), grad_robust=(8, 1, "D"))
    t2 = {**t, "controllable": 8, "excluded": [{"delay_s": 8.0, "alpha": 0.6, "open_loop_diverged_at_s": 6.9}]}
    lines = _map_lines({"paper": {"table": t}, "reference": {"table": t2}}, ["paper", "reference"])
    assert lines[0].startswith("| controller | told |")
    assert "| adaptive backstepping (alpha estimated online) | D | 7 / 1 of 10 | 7 / 1 of 8 |" in lines
    assert any("(D 8 s, alpha 0.6) at t = 6.9 s" in ln for ln in lines)
    assert any("claim 5 re-judged" in ln and "**reproduced**" in ln for ln in lines)


def test_a_law_added_through_the_registry_appears_in_the_maps_and_the_report():
    """Issue 47, item 1: one registry entry, no other edit: the map runs the law, tells it what its entry says,
    and REPORT.md's map table and figures label it; its name is then reserved for --controller."""
    from jaxtraffic.cli import external
    from jaxtraffic.control import lyapunov
    from jaxtraffic.paper import laws

    law = laws.register(laws.Law("lyapunov_k3", "Lyapunov, k = 3 (a user's law)", short="Lyapunov k 3",
                                 style=dict(color="k", ls=":"), build=lambda: lyapunov(3.0), scope="map",
                                 role="a user's row"))
    try:
        cfg = _cfg()
        ctrls = deploy({"open_loop": open_loop(), **map_controllers()}, {}, cfg)
        assert "lyapunov_k3" in ctrls and "lyapunov_k3" not in others(ctrls)
        robust = run_robustness(ctrls, cfg, log=lambda _: None)
        assert list(robust)[-1] == "lyapunov_k3"
        table = map_table(robust, {n: told(n, c) for n, c in ctrls.items()}, cfg)
        assert table["rows"]["lyapunov_k3"] == {**table["rows"]["lyapunov_k3"], "told": "nothing",
                                                "role": "a user's row"}
        report = "\n".join(robustness_summary(robust, cfg, table=table))
        assert "| Lyapunov, k = 3 (a user's law) | nothing |" in report
        from jaxtraffic.paper.plotting import _style
        assert _style("Lyapunov k 3") == {"color": "k", "ls": ":"}
        with pytest.raises(ValueError, match="a registered law"):
            external.parse(["lyapunov_k3=tests/judge_controller.py:policy"])
        with pytest.raises(ValueError, match="registered already"):
            laws.register(law)
    finally:
        laws.unregister("lyapunov_k3")
    assert "lyapunov_k3" not in map_controllers()
