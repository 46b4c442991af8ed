"""The measures of a rollout over its whole horizon and their distributions over scenarios (docs/model.md
section 20).

Per scenario (``per_scenario``), from the density deviation's L2 norm recorded along the rollout:

    mean_rho_L2      veh/km  its time average over [0, T] (trapezoid over the records)
    late_max_rho_L2  veh/km  its maximum over the last half, [T/2, T]
    settle_s         s       the first recorded time after which it stays <= SETTLE_FRACTION x its value at t = 0
                             (inf: not settled by T)
    J_TTT, J_fuel, J_comfort the paper's indices over [0, T] (``UNITS``)
    diverged                 the rollout left the physical region or the controller's output was not finite

A diverged rollout's measures are +inf (the worst), so that medians and intervals rank it last. Over scenarios
(``summarise``): the median of each measure (``np.median``: the mean of the two middle values of an even count;
+inf where either is) with a percentile-bootstrap 95 % interval (``bootstrap_interval``, seeded), the failure
rates (diverged; not settled by T) with Wilson score intervals (``wilson_interval``: not empty at 0 or n
failures), and, against a reference law run on the same scenarios, the ratio of the medians of ``mean_rho_L2``
with a paired-bootstrap interval (``median_ratio``: the scenarios resampled together).
"""

from __future__ import annotations

from collections.abc import Callable
from statistics import NormalDist
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxtraffic.sim.units import INDEX_UNITS

SETTLE_FRACTION = 0.1  # settling: the L2 norm stays below this fraction of its initial value
RECORD_EVERY_S = 5.0  # s: the period at which the measures sample a rollout's L2 norm
L2_CAP = 50.0  # veh/km: a diverged scenario's (or a larger) time-averaged L2 in a fitness (a jam-scale wave)
JS = ("J_TTT", "J_fuel", "J_comfort")
UNITS = {"mean_rho_L2": "veh/km", "late_max_rho_L2": "veh/km", "settle_s": "s", **INDEX_UNITS}
MEASURES = tuple(UNITS)


def settle_times(t: np.ndarray, y: np.ndarray, fraction: float = SETTLE_FRACTION,
                 threshold: np.ndarray | float | None = None) -> np.ndarray:
    """Per row of ``y`` ((B, T) norms recorded at times ``t``, (T,)): the first recorded time after which the row
    stays <= its threshold to the end (t[0] if always; inf if it ends above). The threshold: ``threshold`` ((B,) or
    a scalar) if given, else ``fraction`` x the row's value at t[0]. NaN counts as above."""
    y = np.atleast_2d(np.asarray(y, float))
    thr = fraction * y[:, :1] if threshold is None else np.reshape(np.asarray(threshold, float), (-1, 1))
    above = ~(y <= thr)
    last = np.where(above.any(axis=1), y.shape[1] - 1 - np.argmax(above[:, ::-1], axis=1), -1)
    k = last + 1
    return np.where(k < y.shape[1], np.asarray(t, float)[np.minimum(k, y.shape[1] - 1)], np.inf)


def per_scenario(t: np.ndarray, rho_l2: np.ndarray, diverged: np.ndarray, metrics: dict[str, Any]
                 ) -> dict[str, np.ndarray]:
    """The measures of the module docstring, each (B,): ``t`` (T,) s, ``rho_l2`` (B, T) veh/km, ``diverged`` (B,),
    ``metrics``: the rollouts' J's, each (B,)."""
    t, y = np.asarray(t, float), np.asarray(rho_l2, float)
    div = np.asarray(diverged, bool) | ~np.all(np.isfinite(y), axis=1)
    late = t >= 0.5 * (t[0] + t[-1])
    out = {"mean_rho_L2": np.trapezoid(y, t, axis=1) / (t[-1] - t[0]), "late_max_rho_L2": y[:, late].max(axis=1),
           "settle_s": settle_times(t, y), **{j: np.asarray(metrics[j], float) for j in JS}}
    out = {k: np.where(div, np.inf, v) for k, v in out.items()}
    return {**out, "diverged": div, "not_settled": ~np.isfinite(out["settle_s"])}


def capped(mean_rho_l2: Any, cap: float = L2_CAP) -> np.ndarray:
    """``per_scenario``'s ``mean_rho_L2`` (veh/km; +inf where diverged) at most ``cap``: a diverged or larger
    scenario counts as ``cap`` in a fitness or a selection score (``capped_mean_l2``'s value, from the measures)."""
    return np.minimum(np.asarray(mean_rho_l2, float), cap)


def capped_mean_l2(t: Any, rho_l2: Any, diverged: Any, cap: float = L2_CAP) -> Any:
    """(B,) veh/km: ``per_scenario``'s ``mean_rho_L2`` of norms ``rho_l2`` (B, T) veh/km recorded at ``t`` (T,) s,
    at most ``cap``, and ``cap`` where the rollout diverged or a norm is not finite: the fitness the tuned
    baselines and the CEM-trained learned laws minimise (``compare.tuning``, ``learn.gradient.cem``). Pure
    ``jax.numpy``: it runs inside a compiled training step."""
    y = jnp.asarray(rho_l2)
    mean = jnp.trapezoid(y, jnp.asarray(t), axis=1) / (t[-1] - t[0])
    bad = jnp.asarray(diverged, bool) | ~jnp.all(jnp.isfinite(y), axis=1)
    return jnp.where(bad, cap, jnp.minimum(mean, cap))


def _resamples(n: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, n) indices drawn with replacement (seeded)."""
    return np.random.default_rng(seed).integers(0, n, size=(n_boot, n))


def _percentiles(stats: np.ndarray, level: float) -> tuple[float, float]:
    q = (1 - level) / 2
    return float(np.quantile(stats, q, method="inverted_cdf")), float(np.quantile(stats, 1 - q, method="inverted_cdf"))


def bootstrap_interval(x: np.ndarray, stat: Callable[..., Any] = np.median, n_boot: int = 2000,
                       level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """The percentile-bootstrap ``level`` interval of ``stat`` over the samples ``x`` (resampled ``n_boot`` times
    with replacement, seeded: the same call gives the same interval). +inf samples are kept (a failure ranks
    last)."""
    x = np.asarray(x, float)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"bootstrap_interval needs a non-empty 1-d sample, got shape {x.shape}")
    return _percentiles(stat(x[_resamples(x.size, n_boot, seed)], axis=1), level)


def ratio_or_inf(a: Any, b: Any) -> np.ndarray:
    """a / b with inf / inf (both failed) counted as inf (no better) and x / 0 as inf."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.asarray(a, float) / np.asarray(b, float)
    return np.where(np.isnan(r), np.inf, r)


def median_ratio(a: np.ndarray, b: np.ndarray, n_boot: int = 2000, level: float = 0.95, seed: int = 0
                 ) -> tuple[float, tuple[float, float]]:
    """(median(a) / median(b), its paired-bootstrap ``level`` interval): ``a`` and ``b`` are one measure of two laws
    on the same scenarios (resampled together, seeded); +inf samples rank last."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise ValueError(f"median_ratio needs two 1-d samples of one shape, got {a.shape} and {b.shape}")
    idx = _resamples(a.size, n_boot, seed)
    boot = ratio_or_inf(np.median(a[idx], axis=1), np.median(b[idx], axis=1))
    return float(ratio_or_inf(np.median(a), np.median(b))), _percentiles(boot, level)


def wilson_interval(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The Wilson score ``level`` interval of a rate of ``k`` events in ``n`` trials (not empty at k = 0 or n)."""
    if n <= 0 or not 0 <= k <= n:
        raise ValueError(f"wilson_interval needs 0 <= k <= n, n > 0; got k = {k}, n = {n}")
    z = NormalDist().inv_cdf(0.5 + level / 2)
    p, d = k / n, 1 + z * z / n
    centre, half = (p + z * z / (2 * n)) / d, z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, float(centre - half)), min(1.0, float(centre + half))


def summarise(per: dict[str, np.ndarray], reference: dict[str, np.ndarray] | None = None, seed: int = 0
              ) -> dict[str, Any]:
    """The distribution of ``per`` (``per_scenario``) over its scenarios (module docstring); ``reference``: the
    same scenarios under the reference law (the ratio of the medians of ``mean_rho_L2``)."""
    out: dict[str, Any] = {"n": int(per["diverged"].size)}
    for m in MEASURES:
        out[m] = {"median": float(np.median(per[m])), "ci95": bootstrap_interval(per[m], seed=seed), "unit": UNITS[m]}
    for f in ("diverged", "not_settled"):
        x = np.asarray(per[f], bool)
        out[f"{f}_rate"] = {"value": float(x.mean()), "ci95": wilson_interval(int(x.sum()), x.size)}
    if reference is not None:
        r, ci = median_ratio(per["mean_rho_L2"], reference["mean_rho_L2"], seed=seed)
        out["ratio_mean_rho_L2"] = {"value": r, "ci95": ci}
    return out
