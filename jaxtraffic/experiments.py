"""The paper's experiments (MODEL.md sections 10-12): scenarios, batched evaluation, outputs.

``evaluate.py`` is a thin command line around ``evaluate_all``. Everything here works on a given
set of controllers, so it is independent of how the PPO policy was obtained.

Scenarios (all: the paper's initial condition, nominal model and target = TrafficParams(alpha=0.15)
on the evaluation grid, MODEL.md section 12):

    delay0            plant D = 0                         open_loop, lyapunov, ppo
    delay4            plant D = 4 s                       open_loop, lyapunov, backstepping, ppo
    alpha_noise       plant D = 4 s, alpha + N(0, 0.15^2) backstepping, ppo   (several seeds)
    delay_mismatch_3  plant D = 3 s                       backstepping, ppo   (both assume 4 s)
    delay_mismatch_5  plant D = 5 s                       backstepping, ppo   (both assume 4 s)

Backstepping always assumes D_ctrl = 4 s in these scenarios. All scenarios (and seeds) of one
controller run as one vmapped ``simulate_batch`` call; the robustness map (plant delay x plant
alpha) is one more batched call per controller, with backstepping assuming the true plant delay.

Derived quantities (computed from the recorded trajectories, stride ``record_every`` steps):
    t_settle_rho_s / t_settle_v_s: the first recorded time after which ||rho~||_L2 (resp.
        ||v~||_L2) stays <= SETTLE_FRACTION x its value at t = 0 until the end; None if never.

Verdict criteria for the paper's claims are in ``CRITERIA`` and ``evaluate_claims``.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic import metrics as M
from jaxtraffic.controllers import Controller, backstepping, lyapunov, open_loop
from jaxtraffic.params import TrafficParams, equilibrium, steps_for
from jaxtraffic.rollout import paper_initial_condition, simulate_batch

CTRL_DELAY = 4.0  # s, the delay the controllers (backstepping, PPO) are designed / trained for
NOISE_STD = 0.15  # std of the Gaussian noise on the plant's alpha (alpha_noise scenario)
SETTLE_FRACTION = 0.1  # settling: L2 norm stays below this fraction of its initial value
COMPARABLE_RATIO = 1.5  # "comparable" convergence times: max/min <= this
REL_MARGIN = 0.02  # "less" / "faster": smaller by more than this fraction (ties are not wins)
MATCH_PAPER_REL = 0.5  # an improvement % "matches" the paper's within this relative tolerance
EQUILIBRIUM_TOL = 0.03  # acceptance: J_TTT, J_fuel within 3 % of the equilibrium values

REQUIRED_KEYS = ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward",
                 "time_to_reward_-0.1_s", "diverged", "control_effort")

UNITS = {
    "J_TTT": "veh*s (int int rho dx dt with rho in veh/km, x in m, t in s; paper Table 2 units)",
    "J_fuel": "int int xi(v,a) rho dx dt, xi in ml/s per vehicle, rho in veh/km, x in m, t in s",
    "J_comfort": "int int (a^2 + a_t^2) rho dx dt, a in m/s^2, a_t in m/s^3, rho in veh/km, x in m, t in s",
    "final_rho_L2": "veh/m, sqrt(mean_i (rho_i - rho_bar)^2) at the end of the horizon",
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


@dataclass(frozen=True)
class Scenario:
    """Plant of one scenario: true delay (s), alpha noise std, whether it is averaged over seeds."""

    name: str
    plant_delay: float
    alpha_noise: float
    controllers: tuple[str, ...]
    description: str

    @property
    def seeded(self) -> bool:
        return self.alpha_noise > 0


SCENARIOS = (
    Scenario("delay0", 0.0, 0.0, ("open_loop", "lyapunov", "ppo"), "plant delay D = 0"),
    Scenario("delay4", 4.0, 0.0, ("open_loop", "lyapunov", "backstepping", "ppo"), "plant delay D = 4 s"),
    Scenario("alpha_noise", 4.0, NOISE_STD, ("backstepping", "ppo"),
             f"plant delay D = 4 s, plant alpha = clip(0.15 + N(0, {NOISE_STD}^2), 0, 1) redrawn every step"),
    Scenario("delay_mismatch_3", 3.0, 0.0, ("backstepping", "ppo"),
             "plant delay D = 3 s, controllers assume 4 s"),
    Scenario("delay_mismatch_5", 5.0, 0.0, ("backstepping", "ppo"),
             "plant delay D = 5 s, controllers assume 4 s"),
)
SCENARIO_BY_NAME = {s.name: s for s in SCENARIOS}
ROBUST_CONTROLLERS = ("open_loop", "lyapunov", "backstepping", "ppo")


@dataclass
class EvalConfig:
    """Grid, horizon and sampling of an evaluation.

    ``robust_horizon_s``: horizon of the robustness map, longer than the paper's 300 s because a
    plant whose alpha differs from the nominal one needs about L / v_bar ~ 320 s for the transition
    front towards its own steady state to cross the road; at 300 s the map would show that
    transient rather than (in)stability.
    """

    n_points: int = 201
    dt: float = 0.1
    horizon_s: float = 300.0
    seeds: tuple[int, ...] = tuple(range(8))
    robust_delays: tuple[float, ...] = tuple(np.round(np.linspace(0.0, 8.0, 17), 6))
    robust_alphas: tuple[float, ...] = tuple(np.round(np.linspace(0.05, 0.6, 12), 6))
    record_every_target: int = 10
    robust_horizon_s: float = 600.0

    @property
    def n_steps(self) -> int:
        return steps_for(self.nominal(), self.horizon_s)

    @property
    def record_every(self) -> int:
        """Largest divisor of n_steps that is <= record_every_target."""
        n = self.n_steps
        return max(r for r in range(1, min(self.record_every_target, n) + 1) if n % r == 0)

    @property
    def max_delay_steps(self) -> int:
        worst = max([CTRL_DELAY, *self.robust_delays, *(s.plant_delay for s in SCENARIOS)])
        return max(100, int(math.ceil(round(worst / self.dt, 6))))

    def nominal(self, **changes: Any) -> TrafficParams:
        return TrafficParams(alpha=0.15, n_points=self.n_points, dt=self.dt,
                             max_delay_steps=self.max_delay_steps, **changes)


def robust_axis(n: int, lo: float, hi: float, dt: float | None = None) -> tuple[float, ...]:
    """n evenly spaced values in [lo, hi] (rounded to multiples of dt if given); n = 0: none."""
    vals = np.linspace(lo, hi, n) if n != 1 else np.array([lo])
    if dt is not None:
        vals = np.round(vals / dt) * dt
    return tuple(float(v) for v in np.round(vals, 6))


# ----------------------------------------------------------------------------- batching helpers
def stack_envs(envs: list[TrafficParams]) -> TrafficParams:
    """A batched TrafficParams from concrete per-environment ones.

    Stacks the float fields as float64 numpy arrays so that the construction-time validation
    (e.g. "delay is a multiple of dt") runs in double precision; ``stack_params`` stacks in
    float32, where 7.0 / 0.1 misses the tolerance and delays >= 7 s are wrongly rejected.
    """
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x, np.float64) for x in xs]), *envs)


def _settle_time(t: np.ndarray, y: np.ndarray, threshold: float) -> float | None:
    """First recorded time after which y stays <= threshold to the end; None if y ends above."""
    above = np.nonzero(~(y <= threshold))[0]
    if above.size == 0:
        return float(t[0])
    k = above[-1] + 1
    return float(t[k]) if k < len(t) else None


@dataclass
class Outcome:
    """Result of one (scenario, controller): per-seed metrics and recorded series.

    metrics: name -> array (S,); t: (T,) s (every record_every steps from 0, plus the final time);
    rho, v (veh/m, m/s), h (sent time gap, s): (S, T, N); reward, rho_L2 (veh/m), v_L2 (m/s): (S, T).
    """

    metrics: dict[str, np.ndarray]
    t: np.ndarray
    rho: np.ndarray
    v: np.ndarray
    h: np.ndarray
    reward: np.ndarray
    rho_L2: np.ndarray
    v_L2: np.ndarray
    controller_label: str = ""
    extra: dict = field(default_factory=dict)


def run_batch(controller: Controller, envs: list[TrafficParams], keys: list[int], cfg: EvalConfig,
              record: bool = True, batch_controller: bool = False):
    """One vmapped rollout of ``controller`` over ``envs`` from the paper's initial condition
    (computed on the nominal equilibrium). Returns the SimResult with numpy leaves."""
    nom = cfg.nominal()
    rho0, v0 = paper_initial_condition(nom)
    b = len(envs)
    params = stack_envs(envs)
    res = simulate_batch(
        params, controller, n_steps=cfg.n_steps, nominal=nom,
        rho0=jnp.broadcast_to(rho0, (b, nom.n_points)), v0=jnp.broadcast_to(v0, (b, nom.n_points)),
        keys=jnp.stack([jax.random.PRNGKey(k) for k in keys]),
        record_every=cfg.record_every if record else 0, batch_controller=batch_controller,
    )
    return jax.tree_util.tree_map(np.asarray, res)


def initial_norms(cfg: EvalConfig) -> tuple[float, float]:
    """||rho~(0)||_L2 (veh/m) and ||v~(0)||_L2 (m/s) of the paper's initial condition."""
    nom = cfg.nominal()
    rho_bar, v_bar = equilibrium(nom)
    rho0, v0 = paper_initial_condition(nom)
    return float(M.l2_deviation(rho0, rho_bar)), float(M.l2_deviation(v0, v_bar))


def run_scenarios(controllers: dict[str, Controller], cfg: EvalConfig,
                  log: Callable[[str], None] = print,
                  scenario_controllers: dict[tuple[str, str], Controller] | None = None,
                  ) -> dict[str, dict[str, Outcome]]:
    """Evaluate every scenario; all scenarios and seeds of one controller in one batched rollout.

    ``controllers``: name -> Controller for the names used in SCENARIOS ("ppo" included).
    ``scenario_controllers``: (scenario, name) -> Controller overrides (e.g. a separate D = 0 PPO
    policy for "delay0"); each distinct override runs as its own batch.
    Returns {scenario: {controller name: Outcome}}.
    """
    overrides = scenario_controllers or {}
    groups: dict[tuple[str, str], list[tuple[str, int]]] = {}
    for sc in SCENARIOS:
        for name in sc.controllers:
            gid = (name, sc.name) if (sc.name, name) in overrides else (name, "")
            seeds = cfg.seeds if sc.seeded else (0,)
            groups.setdefault(gid, []).extend((sc.name, s) for s in seeds)
    nom = cfg.nominal()
    results: dict[str, dict[str, Outcome]] = {sc.name: {} for sc in SCENARIOS}
    for (name, override_scenario), members in groups.items():
        ctrl = overrides[(override_scenario, name)] if override_scenario else controllers[name]
        envs = [nom.replace(delay=SCENARIO_BY_NAME[s].plant_delay,
                            alpha_noise=SCENARIO_BY_NAME[s].alpha_noise) for s, _ in members]
        t0 = time.perf_counter()
        res = run_batch(ctrl, envs, [seed for _, seed in members], cfg)
        scen = sorted({s for s, _ in members}, key=[x.name for x in SCENARIOS].index)
        log(f"  {name:<13s} {len(envs):3d} envs x {cfg.n_steps} steps ({', '.join(scen)})"
            f"  {time.perf_counter() - t0:6.1f} s")
        tr, fin, met = res.trajectory, res.final, res.metrics

        def cat(rec, last):  # append the final state (t = T) to the recorded series
            return np.concatenate([rec, np.asarray(last)[:, None]], axis=1)

        t_all = np.append(np.asarray(tr.t[0]), cfg.n_steps * cfg.dt)
        rho, vel, h = cat(tr.rho, fin.rho), cat(tr.v, fin.v), cat(tr.h, fin.h_prev)
        reward = cat(tr.reward, met["final_reward"])
        rho_l2, v_l2 = cat(tr.rho_L2, met["final_rho_L2"]), cat(tr.v_L2, met["final_v_L2"])
        for s in scen:
            idx = np.array([i for i, (sn, _) in enumerate(members) if sn == s])
            results[s][name] = Outcome(
                metrics={k: np.asarray(a)[idx] for k, a in met.items()}, t=t_all, rho=rho[idx], v=vel[idx],
                h=h[idx], reward=reward[idx], rho_L2=rho_l2[idx], v_L2=v_l2[idx],
                controller_label=getattr(ctrl, "name", name),
            )
    return {s: {n: results[s][n] for n in SCENARIO_BY_NAME[s].controllers} for s in results}


def run_robustness(controllers: dict[str, Controller], cfg: EvalConfig,
                   log: Callable[[str], None] = print) -> dict[str, dict[str, np.ndarray]]:
    """Final density L2 over plant delay x plant alpha (no noise), one batched rollout per
    controller. Backstepping assumes the true plant delay (a batched controller setting); the
    other controllers ignore the delay. Returns name -> {"final_rho_L2", "diverged",
    "final_v_L2", "final_reward", "final_rho_spatial_std"} arrays of shape (len(delays),
    len(alphas)); final_rho_spatial_std (veh/m) is the standard deviation over x of the final
    density: the remaining wave amplitude, blind to a uniform offset from the nominal target."""
    if not cfg.robust_delays or not cfg.robust_alphas:
        return {}
    cfg = replace(cfg, horizon_s=cfg.robust_horizon_s)
    nom = cfg.nominal()
    dd, aa = np.meshgrid(np.asarray(cfg.robust_delays), np.asarray(cfg.robust_alphas), indexing="ij")
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(dd.ravel(), aa.ravel(), strict=True)]
    out = {}
    for name in ROBUST_CONTROLLERS:
        if name not in controllers:
            continue
        ctrl, batched = controllers[name], False
        if name == "backstepping":
            ctrl = backstepping(delay=jnp.asarray(dd.ravel(), jnp.float32), k=jnp.ones(dd.size))
            batched = True
        t0 = time.perf_counter()
        res = run_batch(ctrl, envs, [0] * len(envs), cfg, record=False, batch_controller=batched)
        out[name] = {k: np.asarray(res.metrics[k]).reshape(dd.shape)
                     for k in ("final_rho_L2", "final_v_L2", "final_reward", "diverged")}
        out[name]["final_rho_spatial_std"] = np.std(np.asarray(res.final.rho), axis=-1).reshape(dd.shape)
        log(f"  robustness {name:<13s} {len(envs):3d} envs x {cfg.n_steps} steps"
            f"  {time.perf_counter() - t0:6.1f} s")
    return out


# ----------------------------------------------------------------------------- summaries
def _num(x: Any) -> Any:
    """JSON-safe scalar: NaN / inf -> None, numpy -> python."""
    if x is None:
        return None
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    x = float(x)
    return x if math.isfinite(x) else None


def json_safe(obj: Any) -> Any:
    """Recursively convert numpy values and replace NaN / inf by None."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (str, type(None))):
        return obj
    return _num(obj)


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
    for k in ("J_TTT", "J_fuel", "J_comfort", "final_rho_L2", "final_v_L2", "final_reward"):
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
            "time_to_reward_-0.1_s": [_num(x) for x in m["time_to_reward_target_s"]],
            "diverged": [bool(x) for x in div],
            "t_settle_rho_s": settle_r, "t_settle_v_s": settle_v,
        }
    return json_safe(entry)


def equilibrium_indices(cfg: EvalConfig) -> dict[str, float]:
    """J_TTT and J_fuel of the uniform nominal equilibrium over the horizon (rho in veh/km)."""
    nom = cfg.nominal()
    rho_bar, v_bar = (float(x) for x in equilibrium(nom))
    T = cfg.n_steps * cfg.dt
    rho_km = M.VEH_PER_KM * rho_bar
    return {"J_TTT": rho_km * nom.L * T,
            "J_fuel": float(M.fuel_rate(v_bar, 0.0)) * rho_km * nom.L * T,
            "J_comfort": 0.0}


# ----------------------------------------------------------------------------- Table 2
def improvement(ol: float | None, c: float | None) -> float | None:
    """Improvement of c over the open loop ol, in % (positive = better = smaller index)."""
    if ol is None or c is None or ol == 0:
        return None
    return 100.0 * (ol - c) / ol


def table2_rows(metrics: dict, cfg: EvalConfig) -> list[dict[str, Any]]:
    """Rows of Table 2 at D = 4 s: ours, improvement %, the paper's value and improvement."""
    d4 = metrics["delay4"]
    eq = equilibrium_indices(cfg)
    rows = []
    for idx in INDICES:
        row: dict[str, Any] = {"index": idx, "equilibrium": eq[idx] if idx != "J_comfort" else None}
        ol = d4.get("open_loop", {}).get(idx)
        for c in TABLE_CONTROLLERS:
            val = d4.get(c, {}).get(idx)
            row[f"{c}_ours"] = val
            row[f"{c}_paper"] = PAPER_TABLE2[idx][c]
            if c != "open_loop":
                row[f"{c}_improvement_pct_ours"] = improvement(ol, val)
                row[f"{c}_improvement_pct_paper"] = PAPER_IMPROVEMENT[idx][c]
        rows.append(row)
    return rows


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


def write_table2(rows: list[dict[str, Any]], out_dir: Path, horizon_s: float) -> None:
    """table2.csv (all columns) and table2.md (ours next to the paper's, clearly labelled)."""
    cols = list(rows[0])
    with open(out_dir / "table2.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r[k] is None else r[k]) for k in cols})
    lines = [
        f"# Table 2: performance indices, plant delay D = 4 s, first {horizon_s:g} s",
        "",
        "Ours = this reproduction (rho in veh/km, x in m, t in s). **Paper** = the values printed in",
        "the paper's Table 2, quoted for comparison (2 significant digits). Improvement = (J_open_loop",
        "- J) / J_open_loop in %. Equilibrium = the index of the uniform nominal equilibrium over the",
        "same horizon (a lower bound for J_TTT reached only at equilibrium).",
        "",
        "| index | equilibrium | open loop (ours) | open loop (**paper**) | backstepping (ours) "
        "| improvement (ours) | backstepping (**paper**) | improvement (**paper**) | PPO (ours) "
        "| improvement (ours) | PPO (**paper**) | improvement (**paper**) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['index']} | {_fmt(r['equilibrium'])} | {_fmt(r['open_loop_ours'])} "
            f"| {_fmt_paper(r['open_loop_paper'])} "
            f"| {_fmt(r['backstepping_ours'])} | {_fmt(r['backstepping_improvement_pct_ours'], True)} "
            f"| {_fmt_paper(r['backstepping_paper'])} "
            f"| {_fmt_paper(r['backstepping_improvement_pct_paper'], True)} "
            f"| {_fmt(r['ppo_ours'])} | {_fmt(r['ppo_improvement_pct_ours'], True)} "
            f"| {_fmt_paper(r['ppo_paper'])} | {_fmt_paper(r['ppo_improvement_pct_paper'], True)} |")
    (out_dir / "table2.md").write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- claims
CRITERIA = f"""\
Verdicts are computed from the measured numbers; nothing is hard-coded. Each claim is split into
checks; a check passes, fails, or is "not measurable" (missing data, e.g. no learning curve).
Verdict: **reproduced** if every measurable check passes, **not reproduced** if none passes,
**partly** otherwise, **not measured** if no check is measurable.

Definitions used by the checks:
- *stabilised*: the run did not diverge and its reward reached the paper's stop-rule level -0.1
  and stayed there to the end of the horizon (time_to_reward_-0.1_s is not null). For the noise
  scenario this must hold for every seed; *fails* means it holds for fewer than half the seeds.
- *settling time* t_settle of a norm: the time after which ||rho~||_L2 (or ||v~||_L2) stays below
  {SETTLE_FRACTION:g} x its initial value (recorded every record_every steps); never = infinitely slow.
  *Convergence time* = max(t_settle_rho, t_settle_v).
- *faster* / *slower* / *less*: smaller / larger by more than {100 * REL_MARGIN:g} % (relative), so
  ties (e.g. identical controllers) are not wins. *Comparable*: both finite and max/min <=
  {COMPARABLE_RATIO:g}. *A little slower*: slower, with ratio <= 2.
- Table 2 values *match the paper* when they round to the paper's printed 2 significant digits;
  improvements match when within +-{100 * MATCH_PAPER_REL:.0f} % (relative) of the paper's percentage.
- Acceptance (issue 5): J_TTT and J_fuel of backstepping and PPO within {100 * EQUILIBRIUM_TOL:.0f} % of the
  equilibrium values; the open loop worse than both on all three indices.
"""


@dataclass
class Check:
    text: str
    measured: str
    passed: bool | None


def verdict(checks: list[Check]) -> str:
    done = [c.passed for c in checks if c.passed is not None]
    if not done:
        return "not measured"
    if all(done):
        return "reproduced"
    if not any(done):
        return "not reproduced"
    return "partly"


def _t(x: float | None) -> str:
    return "never" if x is None else f"{x:.1f} s"


def _less(a: float, b: float) -> bool:
    """a smaller than b by more than REL_MARGIN (relative to |b|): ties are not wins."""
    return a < b - REL_MARGIN * abs(b)


def _faster(a: float | None, b: float | None) -> bool:
    """Settling time a clearly faster than b (None = never settles)."""
    if a is None:
        return False
    if b is None:
        return True
    return _less(a, b)


def _comparable(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return False
    lo, hi = min(a, b), max(a, b)
    return hi <= COMPARABLE_RATIO * max(lo, 1e-9)


def _conv(e: dict) -> float | None:
    a, b = e.get("t_settle_rho_s"), e.get("t_settle_v_s")
    return None if a is None or b is None else max(a, b)


def stabilised(e: dict) -> bool:
    """Not diverged and the reward reached -0.1 and stayed there (every seed, if seeded)."""
    if e.get("n_seeds", 1) > 1:
        ps = e["per_seed"]
        return all((not d) and (t is not None) for d, t in zip(ps["diverged"], ps["time_to_reward_-0.1_s"],
                                                                  strict=True))
    return (not e["diverged"]) and e["time_to_reward_-0.1_s"] is not None


def stabilised_fraction(e: dict) -> float:
    if e.get("n_seeds", 1) > 1:
        ps = e["per_seed"]
        ok = [(not d) and (t is not None) for d, t in zip(ps["diverged"], ps["time_to_reward_-0.1_s"],
                                                             strict=True)]
        return float(np.mean(ok))
    return 1.0 if stabilised(e) else 0.0


def _stab_text(e: dict) -> str:
    s = "diverged" if e["diverged"] else f"final reward {e['final_reward']:.3g}"
    s += f", reward >= -0.1 from {_t(e['time_to_reward_-0.1_s'])}"
    if e.get("n_seeds", 1) > 1:
        s += f" (mean of {e['n_seeds']} seeds; stabilised in {100 * stabilised_fraction(e):.0f} % of seeds)"
    return s


def evaluate_claims(metrics: dict, cfg: EvalConfig, learning_curve: dict[str, np.ndarray] | None,
                    ppo_d0_label: str) -> list[dict[str, Any]]:
    """Each claim of MODEL.md section 11 with its checks and the computed verdict."""
    d0, d4 = metrics["delay0"], metrics["delay4"]
    an, m3, m5 = metrics["alpha_noise"], metrics["delay_mismatch_3"], metrics["delay_mismatch_5"]
    claims = []

    # 1. learning curve, reward versus time
    checks = []
    if learning_curve is not None and "eval_reward" in learning_curve:
        ev = learning_curve["eval_reward"]
        best = float(np.nanmax(ev)) if np.isfinite(ev).any() else None
        checks.append(Check("training reaches the stop rule (deterministic evaluation reward >= -0.1)",
                            f"best evaluation reward {best:.3g}" if best is not None else "no values",
                            None if best is None else best >= M.REWARD_TARGET))
    else:
        checks.append(Check("training reaches the stop rule (evaluation reward >= -0.1)",
                            "no learning curve available", None))
    checks.append(Check("open loop (D = 4 s) does not converge: reward never stays >= -0.1",
                        _stab_text(d4["open_loop"]), not stabilised(d4["open_loop"])))
    checks.append(Check("PPO (D = 4 s) reward converges to >= -0.1", _stab_text(d4["ppo"]),
                        stabilised(d4["ppo"])))
    ta, tb = d4["ppo"]["time_to_reward_-0.1_s"], d0["ppo"]["time_to_reward_-0.1_s"]
    close = ta is not None and tb is not None and abs(ta - tb) <= max(10.0, 0.25 * min(ta, tb))
    checks.append(Check(f"PPO reward curves with and without delay almost coincide (time to reach -0.1 "
                        f"within max(10 s, 25 %)); D = 0 run uses {ppo_d0_label}",
                        f"D = 4 s: {_t(ta)}, D = 0: {_t(tb)}", close))
    claims.append(dict(id=1, claim="Learning curve of PPO with D = 4 s; reward-versus-time for open loop, "
                       "PPO, backstepping, Lyapunov: the open loop does not converge, PPO converges quickly, "
                       "PPO with and without delay almost coincide.",
                       figures=["fig3a_learning_curve.png", "fig3b_reward.png"], checks=checks))

    # 2. D = 0: Lyapunov vs PPO
    ly, pp = d0["lyapunov"], d0["ppo"]
    checks = [
        Check("Lyapunov stabilises at D = 0", _stab_text(ly), stabilised(ly)),
        Check("PPO stabilises at D = 0", _stab_text(pp), stabilised(pp)),
        Check("PPO converges rho faster than Lyapunov (t_settle_rho)",
              f"PPO {_t(pp['t_settle_rho_s'])} vs Lyapunov {_t(ly['t_settle_rho_s'])}",
              _faster(pp["t_settle_rho_s"], ly["t_settle_rho_s"])),
    ]
    a, b = pp["t_settle_v_s"], ly["t_settle_v_s"]
    checks.append(Check("PPO converges v a little slower than Lyapunov (t_settle_v larger, ratio <= 2)",
                        f"PPO {_t(a)} vs Lyapunov {_t(b)}",
                        a is not None and b is not None and _less(b, a) and a <= 2 * b))
    checks.append(Check("PPO uses less control effort than Lyapunov (RMS of h - h_bar)",
                        f"PPO {pp['control_effort']:.3g} s vs Lyapunov {ly['control_effort']:.3g} s",
                        _less(pp["control_effort"], ly["control_effort"])))
    claims.append(dict(id=2, claim="D = 0: Lyapunov vs PPO; PPO converges rho faster, v a little slower, "
                       "with less control effort.", checks=checks,
                       figures=["fig4_spacetime_delay0.png", "fig4_l2_delay0.png"]))

    # 3. D = 4 s
    ly, bs, pp = d4["lyapunov"], d4["backstepping"], d4["ppo"]
    checks = [
        Check("Lyapunov fails at D = 4 s (not stabilised)", _stab_text(ly), not stabilised(ly)),
        Check("backstepping stabilises at D = 4 s", _stab_text(bs), stabilised(bs)),
        Check("PPO stabilises at D = 4 s", _stab_text(pp), stabilised(pp)),
        Check(f"PPO convergence time comparable to backstepping (ratio <= {COMPARABLE_RATIO:g})",
              f"PPO {_t(_conv(pp))} vs backstepping {_t(_conv(bs))}", _comparable(_conv(pp), _conv(bs))),
        Check("L2 norms: PPO converges the density faster than backstepping",
              f"t_settle_rho: PPO {_t(pp['t_settle_rho_s'])} vs backstepping {_t(bs['t_settle_rho_s'])}",
              _faster(pp["t_settle_rho_s"], bs["t_settle_rho_s"])),
        Check("L2 norms: PPO converges the speed slower than backstepping",
              f"t_settle_v: PPO {_t(pp['t_settle_v_s'])} vs backstepping {_t(bs['t_settle_v_s'])}",
              _faster(bs["t_settle_v_s"], pp["t_settle_v_s"])),
    ]
    claims.append(dict(id=3, claim="D = 4 s: Lyapunov fails, backstepping and PPO stabilise at comparable "
                       "rates; L2 norms: PPO better for density, worse for speed than backstepping.",
                       figures=["fig5_spacetime_delay4.png", "fig6_l2_delay4.png"], checks=checks))

    # 4. Table 2
    eq = equilibrium_indices(cfg)
    checks = []
    for c in ("backstepping", "ppo"):
        for idx in ("J_TTT", "J_fuel"):
            val = d4[c][idx]
            rel = abs(val - eq[idx]) / eq[idx]
            checks.append(Check(f"{c} {idx} within {100 * EQUILIBRIUM_TOL:.0f} % of the equilibrium value "
                                f"{eq[idx]:.4g} (acceptance)", f"{val:.4g} ({100 * rel:.2f} % off)",
                                rel <= EQUILIBRIUM_TOL))
    worse = [d4["open_loop"][i] > max(d4["backstepping"][i], d4["ppo"][i]) for i in INDICES]
    checks.append(Check("open loop worse than backstepping and PPO on all three indices",
                        ", ".join(f"{i}: OL {d4['open_loop'][i]:.3g} / BS {d4['backstepping'][i]:.3g} / "
                                  f"PPO {d4['ppo'][i]:.3g}" for i in INDICES), all(worse)))
    match, txt = [], []
    for idx in INDICES:
        for c in TABLE_CONTROLLERS:
            ours, paper = d4[c][idx], PAPER_TABLE2[idx][c]
            ok = float(f"{ours:.1e}") == paper
            match.append(ok)
            if not ok:
                txt.append(f"{c} {idx} {ours:.1e} vs paper {paper:.1e}")
    checks.append(Check("values round to the paper's printed values (2 significant digits)",
                        f"{sum(match)}/{len(match)} match" + (f"; differ: {'; '.join(txt)}" if txt else ""),
                        all(match)))
    imatch, itxt = [], []
    for idx in INDICES:
        for c in ("backstepping", "ppo"):
            ours = improvement(d4["open_loop"][idx], d4[c][idx])
            paper = PAPER_IMPROVEMENT[idx][c]
            ok = ours is not None and abs(ours - paper) <= MATCH_PAPER_REL * paper
            imatch.append(ok)
            itxt.append(f"{c} {idx} {_fmt(ours, True)} (paper {paper} %)")
    checks.append(Check(f"improvements over the open loop within +-{100 * MATCH_PAPER_REL:.0f} % of the "
                        "paper's", f"{sum(imatch)}/{len(imatch)}: " + "; ".join(itxt), all(imatch)))
    jp, jb = d4["ppo"]["J_comfort"], d4["backstepping"]["J_comfort"]
    checks.append(Check("PPO slightly less comfortable than backstepping (J_comfort larger)",
                        f"PPO {jp:.3g} vs backstepping {jb:.3g}", _less(jb, jp)))
    claims.append(dict(id=4, claim="Table 2 (first 300 s, D = 4 s): open loop 3.4e7 / 8.6e5 / 9.8e5; "
                       "backstepping 3.2e7 / 8.1e5 / 1.3e5; PPO 3.2e7 / 8.1e5 / 1.5e5 (improvements 5.97 %, "
                       "5.80 %, 87.1 % and 84.3 %).", figures=[], tables=["table2.md"], checks=checks))

    # 5. alpha noise
    bs, pp = an["backstepping"], an["ppo"]
    checks = [
        Check("PPO stabilises the plant with alpha noise (every seed)", _stab_text(pp), stabilised(pp)),
        Check("backstepping fails with alpha noise (stabilised in fewer than half the seeds)", _stab_text(bs),
              stabilised_fraction(bs) < 0.5),
    ]
    claims.append(dict(id=5, claim="Robustness: PPO trained at alpha = 0.15, D = 4 s; plant alpha perturbed "
                       "by N(0, 0.15^2) every step: PPO stabilises, backstepping fails.",
                       figures=["fig7_spacetime_alpha_noise.png", "fig7_l2_alpha_noise.png"], checks=checks))

    # 6. mismatched delay
    checks = []
    for name, e in (("D = 3 s", m3), ("D = 5 s", m5)):
        for c in ("backstepping", "ppo"):
            checks.append(Check(f"{c} stabilises with plant {name} (assumes 4 s)", _stab_text(e[c]),
                                stabilised(e[c])))
    checks.append(Check(f"D = 3 s: similar convergence time (ratio <= {COMPARABLE_RATIO:g})",
                        f"PPO {_t(_conv(m3['ppo']))} vs backstepping {_t(_conv(m3['backstepping']))}",
                        _comparable(_conv(m3["ppo"]), _conv(m3["backstepping"]))))
    a, b = _conv(m5["ppo"]), _conv(m5["backstepping"])
    checks.append(Check("D = 5 s: PPO converges slightly better (convergence time <= backstepping's)",
                        f"PPO {_t(a)} vs backstepping {_t(b)}",
                        a is not None and (b is None or a <= b)))
    claims.append(dict(id=6, claim="Mismatched delay (controller assumes 4 s): plant 3 s, both compensate "
                       "with similar rate; plant 5 s, PPO slightly better than backstepping.",
                       figures=["fig8_l2_delay_mismatch.png", "spacetime_delay_mismatch_3.png",
                                "spacetime_delay_mismatch_5.png"], checks=checks))
    for c in claims:
        c["verdict"] = verdict(c["checks"])
    return claims


def robustness_summary(robust: dict[str, dict[str, np.ndarray]], cfg: EvalConfig) -> list[str]:
    """Markdown lines summarising the robustness map (not a claim of the paper)."""
    if not robust:
        return []
    cfg = replace(cfg, horizon_s=cfg.robust_horizon_s)
    r0 = initial_norms(cfg)[0]
    d_idx = [i for i, d in enumerate(cfg.robust_delays) if abs(d - CTRL_DELAY) < 1e-9]
    a_idx = [j for j, a in enumerate(cfg.robust_alphas) if abs(a - 0.15) < 1e-9]
    lines = ["## Robustness map (not in the paper)", "",
             f"Plant delay {min(cfg.robust_delays):g}..{max(cfg.robust_delays):g} s x plant alpha "
             f"{min(cfg.robust_alphas):g}..{max(cfg.robust_alphas):g} ({len(cfg.robust_delays)} x "
             f"{len(cfg.robust_alphas)} cells, no noise), paper initial condition, "
             f"{cfg.n_steps * cfg.dt:g} s. "
             "Backstepping assumes the true plant delay; PPO and Lyapunov ignore the delay. The L2 deviation "
             "is measured from the nominal target (alpha = 0.15), so it includes the steady offset a "
             "proportional law keeps when the plant alpha differs (MODEL.md section 12); the spatial std "
             "of rho measures only the remaining waves (the horizon is longer than the paper's because "
             "such a plant needs about L / v_bar ~ 320 s to settle to its own steady state). "
             "Initial ||rho~||_L2 = "
             f"{1000 * r0:.3g} veh/km.", "",
             "| controller | diverged cells | final rho L2 < initial | final std_x(rho) < 10 % of initial "
             "| final rho L2 at (D = 4 s, alpha = 0.15) (veh/km) |", "|---|---|---|---|---|"]
    for c, r in robust.items():
        div = np.asarray(r["diverged"], bool)
        n = div.size
        below = (~div) & (np.asarray(r["final_rho_L2"]) < r0)
        calm = (~div) & (np.asarray(r["final_rho_spatial_std"]) < SETTLE_FRACTION * r0)
        at = "not on grid"
        if d_idx and a_idx:
            at = f"{1000 * float(r['final_rho_L2'][d_idx[0], a_idx[0]]):.3g}"
        lines.append(f"| {c} | {int(div.sum())}/{n} | {int(below.sum())}/{n} | {int(calm.sum())}/{n} "
                     f"| {at} |")
    return lines + [""]


def write_report(path: Path, claims: list[dict[str, Any]], metrics: dict, meta: dict,
                 figures: list[str], extra_notes: list[str], sections: list[str] | None = None) -> None:
    """REPORT.md: each claim, the checks with measured values and verdicts, the figures embedded;
    ``sections``: further markdown lines (e.g. the robustness summary) before the other figures."""
    lines = ["# Reproduction report: PPO control of congested freeway traffic (paper section 4)", ""]
    pol = meta["policy"]
    lines += [f"- PPO policy: `{pol.get('run_dir')}` ({pol.get('description', '')})",
              f"- PPO in scenario delay0: {meta['policy_delay0']['description']}",
              f"- grid: {meta['grid']['n_points']} points (dx = {meta['grid']['dx_m']:g} m), dt = "
              f"{meta['grid']['dt_s']:g} s, horizon {meta['grid']['horizon_s']:g} s, trajectories recorded "
              f"every {meta['grid']['record_every']} steps; noise seeds {meta['seeds']}",
              f"- runtime: {meta.get('runtime_s', float('nan')):.1f} s", ""]
    lines += extra_notes + ([""] if extra_notes else [])
    lines += ["## Summary", "", "| # | claim | verdict |", "|---|---|---|"]
    for c in claims:
        lines.append(f"| {c['id']} | {c['claim']} | **{c['verdict']}** |")
    lines += ["", "## Criteria", "", CRITERIA, ""]
    for c in claims:
        lines += [f"## Claim {c['id']}: {c['verdict']}", "", f"Paper: {c['claim']}", "",
                  "| check | measured | result |", "|---|---|---|"]
        for ch in c["checks"]:
            res = "not measurable" if ch.passed is None else ("pass" if ch.passed else "FAIL")
            lines.append(f"| {ch.text} | {ch.measured} | {res} |")
        lines.append("")
        for t in c.get("tables", []):
            lines += [f"See [{t}]({t}).", ""]
            tp = path.parent / t
            if tp.exists():
                lines += tp.read_text().splitlines()[2:] + [""]
        for f in c["figures"]:
            if f in figures:
                lines += [f"![{f}]({f})", ""]
    lines += ["## Key numbers per scenario", "",
              "| scenario | controller | J_TTT | J_fuel | J_comfort | final rho L2 (veh/km) "
              "| final v L2 (m/s) | final reward | reward >= -0.1 from | t_settle rho | t_settle v "
              "| effort (s) | diverged |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s, ctrls in metrics.items():
        if s in ("units", "meta"):
            continue
        for c, e in ctrls.items():
            div = "yes" if e["diverged"] else "no"
            if e.get("n_seeds", 1) > 1:
                div = f"{100 * e['diverged_fraction']:.0f} % of {e['n_seeds']} seeds"
            lines.append(
                f"| {s} | {c} | {e['J_TTT']:.4g} | {e['J_fuel']:.4g} | {e['J_comfort']:.3g} "
                f"| {1000 * e['final_rho_L2']:.3g} | {e['final_v_L2']:.3g} | {e['final_reward']:.3g} "
                f"| {_t(e['time_to_reward_-0.1_s'])} | {_t(e['t_settle_rho_s'])} | {_t(e['t_settle_v_s'])} "
                f"| {e['control_effort']:.3g} | {div} |")
    lines += [""] + (sections or [])
    lines += ["## Other figures", ""]
    shown = {f for c in claims for f in c["figures"]}
    for f in figures:
        if f not in shown:
            lines += [f"![{f}]({f})", ""]
    path.write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------- figures
def make_figures(results: dict[str, dict[str, Outcome]], robust: dict[str, dict[str, np.ndarray]],
                 cfg: EvalConfig, out_dir: Path, learning_curve_csv: Path | None,
                 log: Callable[[str], None] = print) -> list[str]:
    """Write every figure into ``out_dir``; returns the file names written."""
    from jaxtraffic import plotting as P

    nom = cfg.nominal()
    rho_bar, v_bar = (float(x) for x in equilibrium(nom))
    eq = (rho_bar, v_bar, float(nom.h_bar))
    x = np.asarray(nom.x())
    lab = P.LABELS
    written: list[str] = []

    def done(p: Path) -> None:
        written.append(p.name)
        log(f"  wrote {p.name}")

    if learning_curve_csv is not None and Path(learning_curve_csv).exists():
        try:
            done(P.plot_learning_curve(learning_curve_csv, out_dir / "fig3a_learning_curve.png",
                                       title="PPO learning curve, D = 4 s (paper fig. 3a)"))
        except ValueError as e:
            log(f"  learning curve not plotted: {e}")
    else:
        log("  no learning_curve.csv: fig3a skipped")

    t = results["delay4"]["open_loop"].t
    series, markers = {}, {}
    for c in ("open_loop", "lyapunov", "backstepping", "ppo"):
        o = results["delay4"][c]
        key = f"{lab[c]} (D = 4 s)"
        series[key] = o.reward[0]
        if o.metrics["diverged"][0]:
            markers[key] = float(o.metrics["diverged_at_s"][0])
    for c in ("lyapunov", "ppo"):
        o = results["delay0"][c]
        key = f"{lab[c]} (D = 0)"
        series[key] = o.reward[0]
        if o.metrics["diverged"][0]:
            markers[key] = float(o.metrics["diverged_at_s"][0])
    done(P.plot_reward(out_dir / "fig3b_reward.png", t, series, markers=markers,
                       title="Reward over time from the paper's initial condition (paper fig. 3b)"))

    titles = {
        "delay0": ("fig4_spacetime_delay0.png", "Plant delay D = 0 (paper fig. 4)"),
        "delay4": ("fig5_spacetime_delay4.png", "Plant delay D = 4 s (paper fig. 5)"),
        "alpha_noise": ("fig7_spacetime_alpha_noise.png",
                        f"D = 4 s, plant alpha = 0.15 + N(0, {NOISE_STD}^2) per step, seed {cfg.seeds[0]} "
                        "(paper fig. 7)"),
        "delay_mismatch_3": ("spacetime_delay_mismatch_3.png", "Plant delay 3 s, controllers assume 4 s"),
        "delay_mismatch_5": ("spacetime_delay_mismatch_5.png", "Plant delay 5 s, controllers assume 4 s"),
    }
    for s, (fname, title) in titles.items():
        rows, div = {}, {}
        for c, o in results[s].items():
            rows[lab[c]] = (o.rho[0], o.v[0], o.h[0])
            if o.metrics["diverged"][0]:
                div[lab[c]] = float(o.metrics["diverged_at_s"][0])
        done(P.plot_spacetime(out_dir / fname, t, x, rows, eq, title, diverged_at=div))

    def l2(s, ctrls):
        return {lab[c]: (results[s][c].rho_L2, results[s][c].v_L2) for c in ctrls}

    done(P.plot_l2_norms(out_dir / "fig4_l2_delay0.png", t, l2("delay0", ("open_loop", "lyapunov", "ppo")),
                         "L2 norms of the deviations, plant delay D = 0"))
    done(P.plot_l2_norms(out_dir / "fig6_l2_delay4.png", t,
                         l2("delay4", ("open_loop", "lyapunov", "backstepping", "ppo")),
                         "L2 norms of the deviations, plant delay D = 4 s (paper fig. 6)"))
    done(P.plot_l2_norms(out_dir / "fig7_l2_alpha_noise.png", t, l2("alpha_noise", ("backstepping", "ppo")),
                         "L2 norms with alpha noise (D = 4 s): mean and min-max band over "
                         f"{len(cfg.seeds)} seeds"))
    done(P.plot_l2_panels(out_dir / "fig8_l2_delay_mismatch.png", t,
                          {"plant D = 3 s": l2("delay_mismatch_3", ("backstepping", "ppo")),
                           "plant D = 5 s": l2("delay_mismatch_5", ("backstepping", "ppo"))},
                          "Mismatched delay, controllers assume 4 s (paper fig. 8)"))
    if robust:
        names = {"open_loop": "open loop", "lyapunov": "Lyapunov",
                 "backstepping": "backstepping (assumes the true plant delay)",
                 "ppo": "PPO (trained D = 4 s)"}
        delays, alphas = np.asarray(cfg.robust_delays), np.asarray(cfg.robust_alphas)
        horizon = replace(cfg, horizon_s=cfg.robust_horizon_s).n_steps * cfg.dt
        maps = {names[c]: (r["final_rho_L2"], r["diverged"]) for c, r in robust.items()}
        done(P.plot_robustness_map(
            out_dir / "robustness_map.png", delays, alphas, maps,
            f"Final density L2 deviation from the nominal target after {horizon:g} s, over plant delay x "
            "plant ACC rate\n(includes the steady offset a proportional law keeps when alpha != 0.15)",
            nominal=(CTRL_DELAY, 0.15), initial_l2=initial_norms(cfg)[0]))
        maps = {names[c]: (r["final_rho_spatial_std"], r["diverged"]) for c, r in robust.items()}
        done(P.plot_robustness_map(
            out_dir / "robustness_map_waves.png", delays, alphas, maps,
            f"Remaining density waves after {horizon:g} s: spatial standard deviation of rho "
            "(blind to a uniform offset)", nominal=(CTRL_DELAY, 0.15), initial_l2=initial_norms(cfg)[0],
            quantity="final std_x(rho) (veh/km)"))
    return written


# ----------------------------------------------------------------------------- driver
def evaluate_all(controllers: dict[str, Controller], cfg: EvalConfig, out_dir: str | Path,
                 meta: dict[str, Any], ppo_delay0: Controller | None = None,
                 learning_curve_csv: str | Path | None = None, log: Callable[[str], None] = print,
                 ) -> dict[str, Any]:
    """Run every scenario and the robustness map, write all outputs; return the metrics dict.

    ``controllers`` must hold "ppo" (the D = 4 s policy); the baselines are added if missing.
    ``ppo_delay0``: a separate policy for scenario delay0 (else the D = 4 s one is used).
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ctrls = {"open_loop": open_loop(), "lyapunov": lyapunov(1.0),
             "backstepping": backstepping(CTRL_DELAY, 1.0)}
    ctrls.update(controllers)
    overrides = {("delay0", "ppo"): ppo_delay0} if ppo_delay0 is not None else {}
    log(f"[1/4] scenarios: {cfg.n_points} points, dt = {cfg.dt} s, {cfg.horizon_s:g} s "
        f"({cfg.n_steps} steps), {len(cfg.seeds)} noise seeds")
    results = run_scenarios(ctrls, cfg, log, overrides)
    log(f"[2/4] robustness map: {len(cfg.robust_delays)} delays x {len(cfg.robust_alphas)} alphas, "
        f"{cfg.robust_horizon_s:g} s" + ("" if cfg.robust_delays and cfg.robust_alphas else " (skipped)"))
    robust = run_robustness(ctrls, cfg, log)

    init_l2 = initial_norms(cfg)
    metrics: dict[str, Any] = {"units": UNITS}
    for s, per in results.items():
        metrics[s] = {c: summarise(o, init_l2) for c, o in per.items()}

    log("[3/4] figures")
    lc = Path(learning_curve_csv) if learning_curve_csv else None
    figures = make_figures(results, robust, cfg, out_dir, lc, log)

    log("[4/4] tables, metrics.json, REPORT.md")
    rows = table2_rows(metrics, cfg)
    write_table2(rows, out_dir, cfg.n_steps * cfg.dt)
    nom = cfg.nominal()
    meta = dict(meta)
    meta.update({
        "seeds": list(cfg.seeds),
        "grid": {"n_points": cfg.n_points, "dx_m": float(nom.dx), "dt_s": cfg.dt, "horizon_s": cfg.horizon_s,
                 "n_steps": cfg.n_steps, "record_every": cfg.record_every},
        "nominal": {"alpha": 0.15, "h_bar_s": float(nom.h_bar),
                    "rho_bar_veh_per_m": float(equilibrium(nom)[0]),
                    "v_bar_m_per_s": float(equilibrium(nom)[1])},
        "initial_L2": {"rho_veh_per_m": init_l2[0], "v_m_per_s": init_l2[1]},
        "scenarios": {s.name: {"plant_delay_s": s.plant_delay, "alpha_noise": s.alpha_noise,
                               "controllers": list(s.controllers), "description": s.description,
                               "controller_assumed_delay_s": CTRL_DELAY} for s in SCENARIOS},
        "equilibrium_indices": equilibrium_indices(cfg),
        "robust_grid": {"delays_s": list(cfg.robust_delays), "alphas": list(cfg.robust_alphas),
                        "horizon_s": cfg.robust_horizon_s},
        "jax_version": jax.__version__, "backend": jax.default_backend(),
    })
    lc_data = None
    if lc is not None and lc.exists():
        from jaxtraffic.plotting import read_learning_curve
        try:
            lc_data = read_learning_curve(lc)
        except ValueError:
            lc_data = None
    d0_label = "a separate D = 0 policy" if ppo_delay0 is not None else "the D = 4 s policy"
    claims = evaluate_claims(metrics, cfg, lc_data, d0_label)
    robust_json = {"delays_s": list(cfg.robust_delays), "alphas": list(cfg.robust_alphas),
                   "horizon_s": cfg.robust_horizon_s,
                   "units": {"final_rho_L2": "veh/m", "final_v_L2": "m/s", "final_reward": "dimensionless",
                             "diverged": "bool", "final_rho_spatial_std": "veh/m"},
                   "note": "arrays indexed [delay][alpha]; backstepping assumes the true plant delay",
                   "controllers": {c: {k: v.tolist() for k, v in r.items()} for c, r in robust.items()}}
    (out_dir / "robustness.json").write_text(json.dumps(json_safe(robust_json), indent=1, allow_nan=False))
    meta["runtime_s"] = time.perf_counter() - t_start
    meta["claims"] = {str(c["id"]): c["verdict"] for c in claims}
    metrics["meta"] = meta
    metrics = json_safe(metrics)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1, allow_nan=False))
    notes = []
    if lc_data is None:
        notes.append("- No learning curve was available, so figure 3a is missing.")
    write_report(out_dir / "REPORT.md", claims, metrics, meta, figures, notes,
                 sections=robustness_summary(robust, cfg))
    (out_dir / "claims.json").write_text(json.dumps(json_safe(
        [{**{k: v for k, v in c.items() if k != "checks"},
          "checks": [ch.__dict__ for ch in c["checks"]]} for c in claims]), indent=1, allow_nan=False))
    log(f"done in {meta['runtime_s']:.1f} s -> {out_dir}")
    return metrics
