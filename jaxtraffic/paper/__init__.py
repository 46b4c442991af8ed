"""The paper's evaluation (imports every layer below): scenarios and batched runs
(``scenarios``), summaries (``summaries``), Table 2 (``table2``), the numerical check of Table 2
(``numerics``), claim verdicts (``claims``), REPORT.md (``report``), figures (``figures``, drawn
by ``plotting``), the driver ``evaluate_all``, the comparison of two plants (``plants``) and the main job's
evaluation on every plant, its REPORT.md written once (``job``)."""

from jaxtraffic.paper.certificate import certificate_section
from jaxtraffic.paper.driver import evaluate_all, evaluate_plant
from jaxtraffic.paper.job import evaluate_plants
from jaxtraffic.paper.plants import compare_plants
from jaxtraffic.paper.scenarios import (
    CTRL_DELAY,
    SCENARIO_BY_NAME,
    SCENARIOS,
    EvalConfig,
    Outcome,
    Scenario,
    robust_axis,
    run_robustness,
    run_scenarios,
)
from jaxtraffic.paper.summaries import REQUIRED_KEYS, summarise
from jaxtraffic.paper.table2 import table2_rows

__all__ = ["CTRL_DELAY", "REQUIRED_KEYS", "SCENARIOS", "SCENARIO_BY_NAME", "EvalConfig", "Outcome", "Scenario",
           "certificate_section", "compare_plants", "evaluate_all", "evaluate_plant", "evaluate_plants", "robust_axis",
           "run_robustness", "run_scenarios", "summarise", "table2_rows"]
