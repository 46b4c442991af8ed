"""Per-(scenario, controller) summaries for metrics.json, settling times, Table 2 (docs/model.md sections 10-11)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxtraffic.compare.stats import settle_times
from jaxtraffic.io.files import to_jsonable
from jaxtraffic.model.params import equilibrium
from jaxtraffic.paper.scenarios import SETTLE_FRACTION, EvalConfig, Outcome
from jaxtraffic.sim.metrics import EXTRA_INDICES, VEH_PER_KM, fuel_rate, fuel_rate_kmh

REQUIRED_KEYS = ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward",
                 "time_to_reward_-0.1_s", "diverged", "control_effort")

UNITS = {
    "J_TTT": "veh/km·m·s = 1e-3 veh·s (int int rho dx dt with rho in veh/km, x in m, t in s; paper Table 2 units)",
    "J_fuel": "int int xi(v,a) rho dx dt, xi in ml/s per vehicle, rho in veh/km, x in m, t in s",
    "J_comfort": "int int (a^2 + a_t^2) rho dx dt, a in m/s^2, a_t in m/s^3, rho in veh/km, x in m, t in s",
    "final_rho_L2": "veh/km, sqrt(mean_i (rho_i - rho_bar)^2) at the end of the horizon",
    "final_v_L2": "m/s, sqrt(mean_i (v_i - v_bar)^2) at the end of the horizon",
    "final_reward": "dimensionless, paper reward -sum_i[(rho~_i/rho_bar)^2 + (v~_i/v_bar)^2] at the end",
    "time_to_reward_-0.1_s": "s, time after which the reward stays >= -0.1 to the end; null if never",
    "diverged": "bool, the state left 0 < rho < 1/l, v >= 0 (run frozen there); any seed",
    "diverged_at_s": "s, time of divergence; null if it never diverged (mean over diverged seeds)",
    "control_effort": "s, RMS over space and time of h_sent - h_bar",
    "t_settle_rho_s": f"s, time after which ||rho~||_L2 stays <= {SETTLE_FRACTION} x its initial value;"
                      " null if never",
    "t_settle_v_s": f"s, time after which ||v~||_L2 stays <= {SETTLE_FRACTION} x its initial value;"
                    " null if never",
    "n_seeds": "number of noise seeds averaged (values are means; 'std' holds the standard deviations)",
    "diverged_fraction": "fraction of seeds that diverged",
    "targets": "every norm, reward and index is measured against the nominal equilibrium (alpha = 0.15)",
    "J_comfort_a2": "the a^2 part of J_comfort (SI, as J_comfort)",
    "J_comfort_at2": "the a_t^2 part of J_comfort (SI); J_comfort_a2 + J_comfort_at2 = J_comfort",
    "J_comfort_switch_on": "the a_t^2 part of the switch-on step n = D/dt, when the first controlled input reaches "
                           "the plant (SI; 0 at D = 0, where a_t(0) := 0)",
    "J_comfort_no_switch_on": "J_comfort - J_comfort_switch_on (SI): J_comfort without the switch-on jerk spike, "
                              "defined the same way for every controller and delay",
    "J_TTT_kmh": "the paper's reading (km/h inside the integrands): equal to J_TTT (rho in veh/km in both)",
    "J_fuel_kmh": "the paper's reading: int int xi(3.6 v, 3.6 a) rho dx dt, i.e. v in km/h and a in km/h/s in the "
                  "b_i terms of xi; xi in ml/s per vehicle, rho in veh/km, x in m, t in s",
    "J_comfort_kmh": "the paper's reading: int int (a^2 + a_t^2) rho dx dt with a in km/h/s, a_t in km/h/s^2 "
                     "(= 3.6^2 x J_comfort); rho in veh/km, x in m, t in s",
    "J_comfort_a2_kmh": "a^2 part of J_comfort_kmh", "J_comfort_at2_kmh": "a_t^2 part of J_comfort_kmh",
    "J_comfort_switch_on_kmh": "J_comfort_switch_on in the km/h reading",
    "J_comfort_no_switch_on_kmh": "J_comfort_no_switch_on in the km/h reading",
    "numerics": "Table 2's scenario (delay4) on a refined grid and with the other scheme; rel_diff = "
                "(J_variant - J) / |J|",
}

# The paper's Table 2 (D = 4 s, first 300 s), quoted as printed in the paper.
PAPER_TABLE2 = {
    "J_TTT": {"open_loop": 3.4e7, "backstepping": 3.2e7, "ppo": 3.2e7},
    "J_fuel": {"open_loop": 8.6e5, "backstepping": 8.1e5, "ppo": 8.1e5},
    "J_comfort": {"open_loop": 9.8e5, "backstepping": 1.3e5, "ppo": 1.5e5},
}
PAPER_IMPROVEMENT = {  # % over the open loop, as printed in the paper
    "J_TTT": {"backstepping": 5.97, "ppo": 5.97},
    "J_fuel": {"backstepping": 5.80, "ppo": 5.80},
    "J_comfort": {"backstepping": 87.1, "ppo": 84.3},
}
TABLE_CONTROLLERS = ("open_loop", "backstepping", "ppo")
INDICES = ("J_TTT", "J_fuel", "J_comfort")


def _settle_time(t: np.ndarray, y: np.ndarray, threshold: float) -> float | None:
    """First recorded time after which y stays <= threshold to the end; None if y ends above."""
    got = float(settle_times(t, y, threshold=threshold)[0])
    return got if np.isfinite(got) else None


def summarise(out: Outcome, init_l2: tuple[float, float]) -> dict[str, Any]:
    """metrics.json entry of one (scenario, controller): means over seeds (std when seeded).

    A time (time to reward, settling) is the mean over seeds when every seed reaches it, null
    otherwise; ``diverged`` is true if any seed diverged.
    """
    m = out.metrics
    n = len(m["J_TTT"])
    settle_r = [_settle_time(out.t, out.rho_L2[i], SETTLE_FRACTION * init_l2[0]) for i in range(n)]
    settle_v = [_settle_time(out.t, out.v_L2[i], SETTLE_FRACTION * init_l2[1]) for i in range(n)]
    div = np.asarray(m["diverged"], bool)
    settle_r = [None if div[i] else s for i, s in enumerate(settle_r)]
    settle_v = [None if div[i] else s for i, s in enumerate(settle_v)]

    def mean_time(vals):
        vals = [None if v is None or not math.isfinite(v) else v for v in vals]
        return None if any(v is None for v in vals) else float(np.mean(vals))

    entry: dict[str, Any] = {}
    for k in ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward", *EXTRA_INDICES):
        if k in m:
            entry[k] = float(np.mean(m[k]))
    entry["time_to_reward_-0.1_s"] = mean_time(list(np.asarray(m["time_to_reward_target_s"], float)))
    entry["diverged"] = bool(div.any())
    entry["control_effort"] = float(np.mean(m["control_effort"]))
    dat = np.asarray(m["diverged_at_s"], float)
    entry["diverged_at_s"] = float(np.mean(dat[div])) if div.any() else None
    entry["t_settle_rho_s"] = mean_time(settle_r)
    entry["t_settle_v_s"] = mean_time(settle_v)
    entry["n_seeds"] = n
    if n > 1:
        entry["diverged_fraction"] = float(div.mean())
        entry["std"] = {k: float(np.std(m[k])) for k in
                        ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward",
                         "control_effort")}
        entry["per_seed"] = {
            "final_rho_L2": [float(x) for x in m["final_rho_L2"]],
            "final_reward": [float(x) for x in m["final_reward"]],
            "time_to_reward_-0.1_s": [to_jsonable(x) for x in m["time_to_reward_target_s"]],
            "diverged": [bool(x) for x in div],
            "t_settle_rho_s": settle_r, "t_settle_v_s": settle_v,
        }
    return to_jsonable(entry)


def equilibrium_indices(eval_config: EvalConfig) -> dict[str, float]:
    """J_TTT and J_fuel of the uniform nominal equilibrium over the horizon (rho in veh/km), in
    both readings (suffix _kmh: the paper's)."""
    nom = eval_config.nominal()
    rho_bar, v_bar = (float(x) for x in equilibrium(nom))
    T = eval_config.n_steps * eval_config.dt
    rho_km = VEH_PER_KM * rho_bar
    return {"J_TTT": rho_km * nom.L * T,
            "J_fuel": float(fuel_rate(v_bar, 0.0)) * rho_km * nom.L * T,
            "J_comfort": 0.0, "J_TTT_kmh": rho_km * nom.L * T,
            "J_fuel_kmh": float(fuel_rate_kmh(v_bar, 0.0)) * rho_km * nom.L * T, "J_comfort_kmh": 0.0}


# ----------------------------------------------------------------------------- Table 2
def improvement(ol: float | None, c: float | None) -> float | None:
    """Improvement of c over the open loop ol, in % (positive = better = smaller index)."""
    if ol is None or c is None or ol == 0:
        return None
    return 100.0 * (ol - c) / ol


def _fmt(x: Any, pct: bool = False, digits: int = 4) -> str:
    """Number for a table: 4 significant digits (``digits``), exponent without '+0'."""
    if x is None:
        return "n/a"
    if pct:
        return f"{x:.2f} %"
    if abs(x) < 1e4:
        return f"{x:.{digits}g}"
    return f"{x:.{digits - 1}e}".replace("e+0", "e").replace("e+", "e")


def _fmt_paper(x: Any, pct: bool = False) -> str:
    """The paper's value as printed (2 significant digits; percentages as printed)."""
    if x is None:
        return "n/a"
    return f"{x:g} %" if pct else _fmt(x, digits=2)
