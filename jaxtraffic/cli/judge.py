"""``evaluate.py --judge --controller NAME=SOURCE:FUNCTION[:ARG]``: judge your own policy against the baselines
without the main job's training.

Every scenario of the paper (``paper.scenarios.SCENARIOS``) runs on each plant of ``--plants`` (the paper grid,
``--n-points`` or 201 points, upwind; the reference plant, ``--reference-grid``, MUSCL) with open loop, Lyapunov,
backstepping and the ``--controller`` policies; no PPO or gradient-trained controller is trained or loaded, no
robustness map, numerics check or claim is made. The outputs go to ``--out`` through the same staging as the main
job (``cli.staging``: an owned folder, replaced whole at the end): judge.json (every scenario's metrics per plant)
and REPORT.md (one table per plant). For the comparison with the learned controllers run the main job with the
same ``--controller`` (``python evaluate.py --controller ...``; it trains the missing runs, or uses those under
``--runs-root`` and ``--run``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jaxtraffic.control import backstepping, lyapunov, open_loop
from jaxtraffic.io.files import atomic_write_text, to_jsonable
from jaxtraffic.io.provenance import provenance
from jaxtraffic.paper.numerics import deploy
from jaxtraffic.paper.scenarios import SCENARIOS, EvalConfig, initial_norms, run_scenarios
from jaxtraffic.paper.summaries import summarise

CTRL_DELAY = 4.0  # the delay backstepping assumes (as in the main job)
COLUMNS = ("J_TTT", "final_rho_L2", "final_v_L2", "final_reward", "diverged")


def judge_plants(own: dict[str, Any], grids: dict[str, Any], configs: dict[str, EvalConfig], out_dir: Path,
                 meta: dict[str, Any], log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every scenario on each plant of ``configs`` for the baselines and ``own`` (name -> Controller, acting on
    ``grids[name]`` when given); writes judge.json and REPORT.md into ``out_dir``; returns judge.json's dict."""
    out_dir.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"meta": {**meta, "controllers": sorted(own), "provenance": provenance()}, "plants": {}}
    for plant, config in configs.items():
        t0 = time.perf_counter()
        log(f"== {plant} plant: {config.describe()}")
        ctrls = {"open_loop": open_loop(), "lyapunov": lyapunov(1.0), "backstepping": backstepping(CTRL_DELAY, 1.0),
                 **own}
        outcomes = run_scenarios(deploy(ctrls, grids, config), config, log)
        init_l2 = initial_norms(config)
        result["plants"][plant] = {
            "config": config.describe(), "runtime_s": time.perf_counter() - t0,
            "scenarios": {s: {c: summarise(o, init_l2) for c, o in per.items()} for s, per in outcomes.items()}}
    result = to_jsonable(result)
    atomic_write_text(out_dir / "judge.json", json.dumps(result, indent=1) + "\n")
    atomic_write_text(out_dir / "REPORT.md", report_text(result))
    return result


def report_text(result: dict[str, Any]) -> str:
    """REPORT.md: one table per plant, a row per (scenario, controller)."""
    lines = ["# Your policy judged against the baselines", "",
             f"Controllers of yours: {', '.join(result['meta']['controllers'])}. No learned controller of "
             "jaxtraffic was trained or evaluated; for that comparison run the main job with the same --controller.",
             ""]
    for plant, res in result["plants"].items():
        lines += [f"## {plant} plant ({res['config']})", "",
                  "| scenario | controller | " + " | ".join(COLUMNS) + " |",
                  "|---|---|" + "---|" * len(COLUMNS)]
        order = [s.name for s in SCENARIOS]
        for s in sorted(res["scenarios"], key=order.index):
            for c, m in res["scenarios"][s].items():
                cells = [_cell(m.get(k)) for k in COLUMNS]
                lines.append(f"| {s} | {c} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)
