"""The claims a held-out comparison supports (docs/model.md section 20), judged from per-scenario measures
(``stats.per_scenario``, one dict per row of the comparison):

* ``seed_lines``: a law trained over several seeds (rows ``<law><sep><seed>``) as the spread of its seeds'
  medians of the time-averaged density L2 (veh/km) and failures; its *median seed* stands for the law below.
* ``base_checks``: a learned law built on a model-based base law, against it on the same scenarios: at least as
  many settled, no more diverged (each seed).
* ``frontier``: the best learned law (a paper-wave row, or a split-trained law's median seed) against the best
  model-based row: the median per-scenario ratio of time-averaged L2 with its paired-bootstrap 95 % interval; the
  frontier is reached when the interval lies below ``FRONTIER`` and it diverges no more often.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from jaxtraffic.compare.stats import bootstrap_interval

FRONTIER = 0.8  # issue 47: a learned law's median time-averaged L2 at most 0.8x the best model-based law's
Results = dict[str, dict[str, np.ndarray]]


def _median(x: np.ndarray, axis: int | None = None) -> Any:
    return np.quantile(x, 0.5, axis=axis, method="inverted_cdf")  # defined with +inf (a failure ranks last)


def medians(res: Results) -> dict[str, float]:
    """Each row's median time-averaged density L2 (veh/km)."""
    return {k: float(_median(r["mean_rho_L2"])) for k, r in res.items()}


def seed_groups(rows: list[str], sep: str) -> dict[str, list[str]]:
    """The rows ``<law><sep><seed>`` grouped by law (other rows left out)."""
    out: dict[str, list[str]] = {}
    for r in rows:
        if sep in r:
            out.setdefault(r.split(sep)[0], []).append(r)
    return out


def median_seed(res: Results, rows: list[str]) -> str:
    """The row whose median time-averaged L2 is the median of ``rows``' (the lower middle of an even count)."""
    med = medians({r: res[r] for r in rows})
    order = sorted(rows, key=lambda r: (med[r], r))
    return order[(len(order) - 1) // 2]


def seed_lines(res: Results, groups: dict[str, list[str]], label: Callable[[str], str]) -> tuple[list[str], dict]:
    """One line per law trained over seeds: its seeds' medians (veh/km), their spread, failures per seed."""
    lines, out = [], {}
    for law, rows in groups.items():
        med = medians({r: res[r] for r in rows})
        vals = [med[r] for r in rows]
        div = [int(res[r]["diverged"].sum()) for r in rows]
        out[law] = {"seeds": rows, "median_mean_rho_L2": vals, "diverged": div, "median_seed": median_seed(res, rows),
                    "spread": [min(vals), max(vals)]}
        lines.append(f"- {label(law)}, trained on the train split over {len(rows)} seeds: median time-averaged L2 "
                     f"{', '.join(f'{v:.3g}' for v in vals)} veh/km (spread {min(vals):.3g}-{max(vals):.3g}), "
                     f"diverged {', '.join(map(str, div))} of {res[rows[0]]['diverged'].size}")
    return lines, out


def base_checks(res: Results, bases: dict[str, str], law_of: Callable[[str], str],
                label: Callable[[str], str]) -> tuple[list[str], dict]:
    """Each row of a law in ``bases`` (law -> its base law's row) against its base: at least as many scenarios
    settled, no more diverged."""
    lines, out = [], {}
    for row in res:
        base = bases.get(law_of(row))
        if base is None or base not in res:
            continue
        a, b = res[row], res[base]
        settled = (int((~a["not_settled"]).sum()), int((~b["not_settled"]).sum()))
        div = (int(a["diverged"].sum()), int(b["diverged"].sum()))
        ok = settled[0] >= settled[1] and div[0] <= div[1]
        out[f"{row}_vs_{base}"] = ok
        lines.append(f"- {label(row)} against its base, {label(base)}: settled {settled[0]} vs {settled[1]} of "
                     f"{a['diverged'].size}, diverged {div[0]} vs {div[1]}: **{'holds' if ok else 'fails'}**")
    return lines, out


def frontier(res: Results, learned: list[str], model: list[str], label: Callable[[str], str]
             ) -> tuple[list[str], dict]:
    """The best of ``learned`` (rows standing for learned laws) against the best of ``model`` (module docstring)."""
    if not learned or not model:
        return [], {}
    med = medians(res)
    best_m, best_l = min(model, key=med.__getitem__), min(learned, key=med.__getitem__)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = res[best_l]["mean_rho_L2"] / res[best_m]["mean_rho_L2"]
    ratio = np.where(np.isnan(ratio), np.inf, ratio)  # both failed: no better
    r, (lo, hi) = float(_median(ratio)), bootstrap_interval(ratio, _median)
    fails = (int(res[best_l]["diverged"].sum()), int(res[best_m]["diverged"].sum()))
    reached = hi < FRONTIER and fails[0] <= fails[1]
    line = (f"- The best learned law, {label(best_l)} (median time-averaged L2 {med[best_l]:.3g} veh/km), against the "
            f"best model-based law, {label(best_m)} ({med[best_m]:.3g} veh/km): median per-scenario ratio {r:.3g} "
            f"[{lo:.3g}, {hi:.3g}], diverged {fails[0]} vs {fails[1]}: the frontier (at most {FRONTIER}x, interval "
            f"below it, no more failures) is **{'reached' if reached else 'not reached'}**")
    return [line], {"best_model_based": best_m, "best_learned": best_l, "ratio": r, "ratio_ci95": [lo, hi],
                    "frontier": reached}
