"""The claims a held-out comparison supports (docs/model.md section 20), judged from per-scenario measures
(``stats.per_scenario``, one dict per row of the comparison):

* ``seed_lines``: a law trained over several seeds (rows ``<law><sep><seed>``) as the spread of its seeds'
  medians of the time-averaged density L2 (veh/km) and failures; its *median seed* stands for the law below.
* ``base_checks``: a learned law built on a model-based base law, against it on the same scenarios: at least as
  many settled, no more diverged (each seed).
* ``frontier``: the best learned law (a paper-wave row, or a split-trained law's median seed) against the best
  model-based row, as issue 47 defines it: the ratio of their medians of the time-averaged density L2 (with its
  paired-bootstrap 95 % interval) at most ``FRONTIER``, the learned law's median interval wholly below the other's
  (the intervals apart), and no more failures
  (diverged, and not settled by the horizon). The median of the per-scenario ratios (paired) is reported beside it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from jaxtraffic.compare.stats import bootstrap_interval, median_ratio, ratio_or_inf

FRONTIER = 0.8  # issue 47: a learned law's median time-averaged L2 at most 0.8x the best model-based law's
Results = dict[str, dict[str, np.ndarray]]


def medians(res: Results) -> dict[str, float]:
    """Each row's median time-averaged density L2 (veh/km; +inf when its middle scenarios diverged)."""
    return {k: float(np.median(r["mean_rho_L2"])) for k, r in res.items()}


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
    a, b = res[best_l], res[best_m]
    r, (lo, hi) = median_ratio(a["mean_rho_L2"], b["mean_rho_L2"])
    ci_l, ci_m = bootstrap_interval(a["mean_rho_L2"]), bootstrap_interval(b["mean_rho_L2"])
    per = ratio_or_inf(a["mean_rho_L2"], b["mean_rho_L2"])
    pr, (plo, phi) = float(np.median(per)), bootstrap_interval(per)
    fails = {f: (int(a[f].sum()), int(b[f].sum())) for f in ("diverged", "not_settled")}
    apart = ci_l[1] < ci_m[0] or ci_m[1] < ci_l[0]
    reached = r <= FRONTIER and ci_l[1] < ci_m[0] and all(x <= y for x, y in fails.values())
    line = (f"- The best learned law, {label(best_l)} (median time-averaged L2 {med[best_l]:.3g} [{ci_l[0]:.3g}, "
            f"{ci_l[1]:.3g}] veh/km), against the best model-based law, {label(best_m)} ({med[best_m]:.3g} "
            f"[{ci_m[0]:.3g}, {ci_m[1]:.3g}] veh/km): ratio of the medians {r:.3g} [{lo:.3g}, {hi:.3g}], the "
            f"intervals {'apart' if apart else 'overlapping'}; diverged {fails['diverged'][0]} vs "
            f"{fails['diverged'][1]}, not settled {fails['not_settled'][0]} vs {fails['not_settled'][1]} (per "
            f"scenario, the median ratio is {pr:.3g} [{plo:.3g}, {phi:.3g}]): the frontier (a ratio at most "
            f"{FRONTIER}x, the intervals apart, no more failures) is **{'reached' if reached else 'not reached'}**")
    return [line], {"best_model_based": best_m, "best_learned": best_l, "ratio": r, "ratio_ci95": [lo, hi],
                    "median_ci95": {"learned": list(ci_l), "model_based": list(ci_m)}, "intervals_apart": apart,
                    "failures": {f: list(v) for f, v in fails.items()}, "ratio_per_scenario": pr,
                    "ratio_per_scenario_ci95": [plo, phi], "frontier": reached}
