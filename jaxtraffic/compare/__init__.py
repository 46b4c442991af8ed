"""The fair comparison of control laws (docs/model.md section 20): a distribution of scenarios split into a train
and a test half (``scenarios``), the measures of one rollout over its whole horizon and their distributions with
bootstrap intervals (``stats``), and the protocol that runs laws over a split on a plant (``protocol``).

Layer: above ``sim`` and ``control``, below the trainers and the paper's experiments, which draw from it."""

from jaxtraffic.compare import verdicts
from jaxtraffic.compare.protocol import LawSpec, delay_order, evaluate_laws, summary_table
from jaxtraffic.compare.scenarios import SPLITS, EpisodePool, ScenarioDistribution, Scenarios, sample
from jaxtraffic.compare.stats import (
    bootstrap_interval,
    median_ratio,
    per_scenario,
    settle_times,
    summarise,
    wilson_interval,
)

__all__ = ["SPLITS", "EpisodePool", "LawSpec", "ScenarioDistribution", "Scenarios", "bootstrap_interval",
           "delay_order", "evaluate_laws", "median_ratio", "per_scenario", "sample", "settle_times", "summarise",
           "summary_table", "verdicts", "wilson_interval"]
