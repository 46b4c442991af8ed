"""The paper's evaluation (imports every layer below): scenarios and batched runs
(``scenarios``), summaries and Table 2 (``summaries``), claim verdicts (``claims``), REPORT.md
(``report``), figures (``figures``, drawn by ``plotting``) and the driver ``evaluate_all``."""

from jaxtraffic.paper.driver import evaluate_all
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
from jaxtraffic.paper.summaries import REQUIRED_KEYS, summarise, table2_rows

__all__ = ["CTRL_DELAY", "REQUIRED_KEYS", "SCENARIOS", "SCENARIO_BY_NAME", "EvalConfig", "Outcome", "Scenario",
           "evaluate_all", "robust_axis", "run_robustness", "run_scenarios", "summarise", "table2_rows"]
