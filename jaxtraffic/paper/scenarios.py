"""The paper's experiments (docs/model.md sections 10-12): scenarios, batched evaluation, outputs.

``evaluate.py`` (``cli.evaluate``) is a thin command line around ``paper.driver.evaluate_all``.
Everything here works on a given set of controllers, so it is independent of how the PPO policy
was obtained.

Scenarios (all: the paper's initial condition, nominal model and target = TrafficParams(alpha=0.15)
on the evaluation grid, docs/model.md section 12):

    delay0            plant D = 0                         open_loop, lyapunov, ppo
    delay4            plant D = 4 s                       open_loop, lyapunov, backstepping, ppo
    alpha_noise       plant D = 4 s, alpha + N(0, 0.15^2) backstepping, ppo   (several seeds)
                      one road-wide draw per step, plant only
    alpha_noise_held_1s / _held_10s   the same, one draw held for 1 s / 10 s
    alpha_noise_node_held_10s         an independent draw per grid node, held 10 s
    alpha_noise_model_sees            per step, and the model-based controllers' nominal alpha is
                                      the noisy plant alpha (``MODEL_BASED``; target fixed)
    delay_mismatch_3  plant D = 3 s                       backstepping, ppo   (both assume 4 s)
    delay_mismatch_5  plant D = 5 s                       backstepping, ppo   (both assume 4 s)

Backstepping always assumes D_ctrl = 4 s in these scenarios. All scenarios (and seeds) of one
controller run as one vmapped ``simulate_batch`` call; the robustness map (plant delay x plant
alpha) is one more batched call per controller, with backstepping assuming the true plant delay.

Derived quantities (computed from the recorded trajectories, stride ``record_every`` steps):
    t_settle_rho_s / t_settle_v_s: the first recorded time after which ||rho~||_L2 (resp.
        ||v~||_L2) stays <= SETTLE_FRACTION x its value at t = 0 until the end; None if never.

Summaries and Table 2: ``paper.summaries``; claim verdicts: ``paper.claims``; REPORT.md:
``paper.report``; figures: ``paper.figures``."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.compare.stats import SETTLE_FRACTION  # noqa: F401 (the paper's modules read it here)
from jaxtraffic.control import Controller, takes_delay, tell_delay
from jaxtraffic.model.params import TrafficParams, equilibrium, steps_for
from jaxtraffic.paper import laws
from jaxtraffic.paper.cells import paper_column, snapshot_every
from jaxtraffic.paper.laws import CTRL_DELAY
from jaxtraffic.runs.session import eta_text
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM, density_l2, l2_deviation
from jaxtraffic.sim.options import AlphaInput, Memory, Record
from jaxtraffic.sim.plant import NoiseReading
from jaxtraffic.sim.rollout import plant_alphas, simulate_batch, stack_params
from jaxtraffic.sim.sharding import host_mesh

# what the robustness map reads of each rollout's final state (no running sums in the loop)
ROBUST_METRICS = ("final_rho_L2", "final_v_L2", "final_reward", "diverged")
# ... and the one running maximum it reads: std_x(rho) over the last 150 s (``sim.metrics.LATE_WINDOW_S``)
MAP_METRICS = (*ROBUST_METRICS, "late_max_rho_std")
NOISE_STD = 0.15  # std of the Gaussian noise on the plant's alpha (alpha_noise scenario)
MODEL_BASED = ("lyapunov", "backstepping")  # controllers with a model alpha (PPO only normalises by the target)


@dataclass(frozen=True)
class Scenario:
    """Plant of one scenario: true delay (s), alpha noise std, whether it is averaged over seeds."""

    name: str
    plant_delay: float
    alpha_noise: float
    controllers: tuple[str, ...]
    description: str
    noise_hold_s: float = 0.0  # each draw held this long (0: redrawn every step)
    noise_per_node: bool = False  # an independent draw per grid node
    noise_model_sees: bool = False  # the model-based controllers' nominal alpha is the plant's

    @property
    def seeded(self) -> bool:
        return self.alpha_noise > 0

    def reading(self, dt: float, controller: str) -> NoiseReading | None:
        """The ``NoiseReading`` of this scenario for ``controller`` (None: the default reading)."""
        r = NoiseReading(hold_steps=max(1, int(round(self.noise_hold_s / dt))), per_node=self.noise_per_node,
                         model_sees=self.noise_model_sees and controller in MODEL_BASED)
        return None if r == NoiseReading() else r


# the paper's scenarios' laws, from the registry (``paper.laws``): the learned ones beyond the paper's PPO
# (evaluated wherever PPO is when they are given), the model-based ones, and those on the robustness map only
_L = laws.names(learned=True)
EXTRA_LEARNED = tuple(n for n in _L if n != "ppo")
BASELINES = laws.names(learned=False, scope="all")
MAP_ONLY = laws.names(scope="map")


def others(names) -> tuple[str, ...]:
    """The names among ``names`` that are neither a baseline nor one of jaxtraffic's learned controllers: the
    controllers a user brings (``evaluate.py --controller``, e.g. a policy trained elsewhere), evaluated
    wherever PPO is, in the order given."""
    return tuple(n for n in names if n not in laws.LAWS)


def learned(names) -> tuple[str, ...]:
    """The learned controllers among ``names``: the registry's learned laws (in its order), then ``others``."""
    names = tuple(names)
    return tuple(n for n in laws.names(learned=True) if n in names) + others(names)


SCENARIOS = (
    Scenario("delay0", 0.0, 0.0, ("open_loop", "lyapunov", *_L), "plant delay D = 0"),
    Scenario("delay4", 4.0, 0.0, ("open_loop", "lyapunov", "backstepping", *_L), "plant delay D = 4 s"),
    Scenario("alpha_noise", 4.0, NOISE_STD, ("backstepping", *_L),
             f"plant delay D = 4 s, plant alpha = clip(0.15 + N(0, {NOISE_STD}^2), 0, 1) redrawn every step"),
    Scenario("alpha_noise_held_1s", 4.0, NOISE_STD, ("backstepping", *_L),
             "as alpha_noise, each draw held for 1 s", noise_hold_s=1.0),
    Scenario("alpha_noise_held_10s", 4.0, NOISE_STD, ("backstepping", *_L),
             "as alpha_noise, each draw held for 10 s", noise_hold_s=10.0),
    Scenario("alpha_noise_node_held_10s", 4.0, NOISE_STD, ("backstepping", *_L),
             "as alpha_noise, an independent draw at every grid node, each held for 10 s",
             noise_hold_s=10.0, noise_per_node=True),
    Scenario("alpha_noise_model_sees", 4.0, NOISE_STD, ("backstepping", *_L),
             "as alpha_noise, and backstepping's nominal alpha is the noisy plant alpha (its model and the "
             "equilibrium it linearises about follow the noise; rewards and indices keep the nominal target); "
             "the learned controllers have no model alpha", noise_model_sees=True),
    Scenario("delay_mismatch_3", 3.0, 0.0, ("backstepping", *_L),
             "plant delay D = 3 s, controllers assume 4 s"),
    Scenario("delay_mismatch_5", 5.0, 0.0, ("backstepping", *_L),
             "plant delay D = 5 s, controllers assume 4 s"),
)
SCENARIO_BY_NAME = {s.name: s for s in SCENARIOS}
NOISE_SCENARIOS = tuple(s.name for s in SCENARIOS if s.seeded)  # the readings of the alpha noise (claim 5)


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
    scheme: str = "upwind"
    substeps: int = 1
    numerics_check: bool = True

    @classmethod
    def reference(cls, **changes: Any) -> EvalConfig:
        """The evaluation on the reference plant (``TrafficParams.reference``'s discretisation)."""
        ref = TrafficParams.reference()
        return cls(**{"n_points": ref.n_points, "scheme": ref.scheme, "substeps": ref.substeps, "dt": float(ref.dt),
                      **changes})

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
        """The nominal plant of the evaluation (alpha 0.15) on its grid."""
        return TrafficParams(alpha=0.15, n_points=self.n_points, dt=self.dt, scheme=self.scheme,
                             substeps=self.substeps, max_delay_steps=self.max_delay_steps, **changes)

    def describe(self) -> str:
        """One line: points, scheme, dx and the solver step."""
        nom = self.nominal()
        return (f"{self.n_points} points ({self.scheme}, dx = {float(nom.dx):g} m), dt = {self.dt:g} s"
                + (f" in {self.substeps} solver steps" if self.substeps > 1 else ""))


def robust_axis(n: int, lo: float, hi: float, dt: float | None = None) -> tuple[float, ...]:
    """n evenly spaced values in [lo, hi] (rounded to multiples of dt if given); n = 0: none."""
    vals = np.linspace(lo, hi, n) if n != 1 else np.array([lo])
    if dt is not None:
        vals = np.round(vals / dt) * dt
    return tuple(float(v) for v in np.round(vals, 6))


@dataclass
class Outcome:
    """Result of one (scenario, controller): per-seed metrics and recorded series.

    metrics: name -> array (S,); t: (T,) s (every record_every steps from 0, plus the final time);
    rho, v (veh/m, m/s), h (sent time gap, s): (S, T, N); reward, rho_L2 (veh/km), v_L2 (m/s): (S, T).
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


def run_batch(controller: Controller, envs: list[TrafficParams], keys: list[int], eval_config: EvalConfig,
              record: bool = True, batch_controller: bool = False, noise: NoiseReading | None = None,
              chunk_size: int | None = None, readings: list[NoiseReading | None] | None = None,
              metrics: tuple[str, ...] | None = None, every: int | None = None):
    """One vmapped rollout of ``controller`` over ``envs`` from the paper's initial condition
    (computed on the nominal equilibrium; ``chunk_size``: see ``simulate_batch``, whose default
    None leaves). ``readings``: per environment, a road-wide reading whose alpha draw it gets
    (``plant_alphas``; ``noise`` then only carries ``model_sees``), so that environments of
    different holding times share one program. ``metrics``: the metrics computed (default all; see
    ``simulate``). ``every``: the recording stride in steps (default ``eval_config.record_every``).
    Returns the SimResult with numpy leaves."""
    nom = eval_config.nominal()
    rho0, v0 = paper_initial_condition(nom)
    b = len(envs)
    params = stack_params(*envs)
    alphas = None
    if readings is not None:
        alphas = jnp.stack([plant_alphas(e, jax.random.PRNGKey(k), eval_config.n_steps, r)
                            for e, k, r in zip(envs, keys, readings, strict=True)])
    res = simulate_batch(
        params, controller, n_steps=eval_config.n_steps, nominal=nom,
        rho0=jnp.broadcast_to(rho0, (b, nom.n_points)), v0=jnp.broadcast_to(v0, (b, nom.n_points)),
        keys=jnp.stack([jax.random.PRNGKey(k) for k in keys]),
        batch_controller=batch_controller, record=Record(every=(every or eval_config.record_every) if record else 0),
        memory=Memory() if chunk_size is None else Memory(chunk_size=chunk_size),
        alpha_input=AlphaInput(alphas=alphas, noise=noise), metrics=metrics,
    )
    return jax.tree_util.tree_map(np.asarray, res)


def _program_reading(reading: NoiseReading | None) -> NoiseReading | None:
    """The reading a scenario's program is compiled for: a road-wide held reading shares the
    default one's program (its alphas are given), the others keep theirs."""
    if reading is None or reading.per_node or reading.hold_steps == 1:
        return reading
    shared = replace(reading, hold_steps=1)
    return None if shared == NoiseReading() else shared


def initial_norms(eval_config: EvalConfig) -> tuple[float, float]:
    """||rho~(0)||_L2 (veh/km) and ||v~(0)||_L2 (m/s) of the paper's initial condition."""
    nom = eval_config.nominal()
    rho_bar, v_bar = equilibrium(nom)
    rho0, v0 = paper_initial_condition(nom)
    return float(density_l2(rho0, rho_bar)), float(l2_deviation(v0, v_bar))


def run_scenarios(controllers: dict[str, Controller], eval_config: EvalConfig,
                  log: Callable[[str], None] = print,
                  scenario_controllers: dict[tuple[str, str], Controller] | None = None,
                  ) -> dict[str, dict[str, Outcome]]:
    """Evaluate every scenario; all scenarios and seeds of one controller in one batched rollout.

    ``controllers``: name -> Controller for the names used in SCENARIOS ("ppo" included; the
    ``EXTRA_LEARNED`` ones are evaluated when given, skipped otherwise), and any other name (``others``),
    evaluated wherever PPO is.
    ``scenario_controllers``: (scenario, name) -> Controller overrides (e.g. a separate D = 0 PPO
    policy for "delay0"); each distinct override runs as its own batch, and so does each reading
    of the alpha noise other than the default one (``Scenario.reading``).
    Readings that differ only in how long a road-wide draw is held share one program (their
    alphas are drawn outside it, ``run_batch(readings=...)``); the per-node and model-sees
    readings have programs of their own.
    Returns {scenario: {controller name: Outcome}}.
    """
    overrides = scenario_controllers or {}
    groups: dict[tuple[str, str, NoiseReading | None], list[tuple[str, int]]] = {}
    for sc in SCENARIOS:
        for name in (*sc.controllers, *(others(controllers) if "ppo" in sc.controllers else ())):
            if name in _L and name not in controllers:  # a learned one not given (judge: no PPO)
                continue
            gid = (name, sc.name if (sc.name, name) in overrides else "", _program_reading(sc.reading(eval_config.dt,
                                                                                                      name)))
            seeds = eval_config.seeds if sc.seeded else (0,)
            groups.setdefault(gid, []).extend((sc.name, s) for s in seeds)
    nom = eval_config.nominal()
    results: dict[str, dict[str, Outcome]] = {sc.name: {} for sc in SCENARIOS}
    total, done, t_start = sum(map(len, groups.values())), 0, time.perf_counter()  # (rollouts)
    for (name, override_scenario, reading), members in groups.items():
        ctrl = overrides[(override_scenario, name)] if override_scenario else controllers[name]
        envs = [nom.replace(delay=SCENARIO_BY_NAME[s].plant_delay,
                            alpha_noise=SCENARIO_BY_NAME[s].alpha_noise) for s, _ in members]
        readings = [SCENARIO_BY_NAME[s].reading(eval_config.dt, name) for s, _ in members]
        shared = any(r != reading for r in readings)  # some member's draw differs from the program's
        t0 = time.perf_counter()
        res = run_batch(ctrl, envs, [seed for _, seed in members], eval_config, noise=reading,
                        readings=readings if shared else None)
        scen = sorted({s for s, _ in members}, key=[x.name for x in SCENARIOS].index)
        done += len(envs)
        log(f"  {name:<13s} {len(envs):3d} envs x {eval_config.n_steps} steps ({', '.join(scen)})"
            f"  {time.perf_counter() - t0:6.1f} s | {_eta(total - done, done, t_start)}")
        tr, fin, met = res.trajectory, res.final, res.metrics

        def cat(rec, last):  # append the final state (t = T) to the recorded series
            return np.concatenate([rec, np.asarray(last)[:, None]], axis=1)

        t_all = np.append(np.asarray(tr.t[0]), eval_config.n_steps * eval_config.dt)
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
    return {s: {n: results[s][n] for n in (*SCENARIO_BY_NAME[s].controllers, *others(controllers)) if n in results[s]}
            for s in results}


def _eta(remaining: int, done: int, t_start: float) -> str:
    """The ETA of this step's ``remaining`` rollouts (or batches) at the rate of the ``done`` ones since
    ``t_start`` (``time.perf_counter``; compilation included: each controller compiles its own program)."""
    return eta_text(remaining, done / max(1e-9, time.perf_counter() - t_start))


def told(name: str, controller: Controller) -> str:
    """What ``controller`` (named ``name``) is told on the robustness map: "D, alpha" (a law registered so told),
    "D" (it takes the delay it compensates, ``control.takes_delay``: backstepping, the adaptive law, a delay
    schedule) or "nothing" (the open loop, Lyapunov, a law trained at one delay)."""
    if name in laws.LAWS and laws.LAWS[name].told == "delay_alpha":
        return "D, alpha"
    return "D" if takes_delay(controller) else "nothing"


def run_robustness(controllers: dict[str, Controller], eval_config: EvalConfig,
                   log: Callable[[str], None] = print) -> dict[str, dict[str, np.ndarray]]:
    """Final density L2 over plant delay x plant alpha (no noise), one batched rollout per
    controller (each acting on ``eval_config``'s plant, e.g. through ``numerics.deploy``). A controller told
    the delay it compensates (``control.takes_delay``: backstepping, a delay schedule) is told the
    true plant delay (a batched controller setting); the others ignore the delay. Returns name ->
    {"final_rho_L2", "diverged", "final_v_L2", "final_reward",
    "final_rho_spatial_std", "final_rho_offset"} arrays of shape (len(delays), len(alphas));
    final_rho_spatial_std (veh/km) is the standard deviation over x of the final density: the
    remaining wave amplitude, blind to a uniform offset from the nominal target;
    final_rho_offset (veh/km) is the final density's mean over x minus the plant's own
    equilibrium density (its alpha, the nominal time gap h_bar: where the open loop would rest);
    "diverged_step": the plant step at which it diverged (-1: never), "diverged_at_s" (s, inf: never);
    "late_max_rho_spatial_std" (veh/km): the maximum of std_x(rho) over the last 150 s of the horizon
    (``sim.metrics.late_max``; inf where it diverged); and the paper's column, the same rollout at the paper's
    horizon (``eval_config.horizon_s``, 300 s; ``cells.paper_column``): "paper_rho_L2", "paper_rho_spatial_std"
    (veh/km), "paper_diverged" (diverged by then). A law registered as told "delay_alpha" (the map's information
    bound) is also told each cell's plant alpha (its ``alpha0``, not adapted)."""
    if not eval_config.robust_delays or not eval_config.robust_alphas:
        return {}
    n_paper = eval_config.n_steps
    eval_config = replace(eval_config, horizon_s=eval_config.robust_horizon_s)
    every = snapshot_every(n_paper, eval_config.n_steps)
    nom = eval_config.nominal()
    dd, aa = np.meshgrid(np.asarray(eval_config.robust_delays), np.asarray(eval_config.robust_alphas), indexing="ij")
    envs = [nom.replace(delay=float(d), alpha=float(a)) for d, a in zip(dd.ravel(), aa.ravel(), strict=True)]
    own_rho = np.array([float(equilibrium(e)[0]) for e in envs]).reshape(dd.shape)  # veh/m, at h_bar
    out = {}
    names = [n for n in (*laws.LAWS, *others(controllers)) if n in controllers]
    t_start = time.perf_counter()
    for i, name in enumerate(names):
        ctrl, batched, chunk = controllers[name], False, None
        law = laws.LAWS.get(name)
        if law is not None and law.predictor and jax.default_backend() == "cpu":
            # the predictor's loop runs to the largest assumed delay of its chunk: one delay per
            # chunk (the batch is delay-major and dealt over the devices), 20 % faster than 64 (on an
            # accelerator the predictor runs a static bound, masked, and the batch is one vmap: Memory's "auto")
            chunk = -(-dd.shape[1] // host_mesh().size)
        if takes_delay(ctrl):
            ctrl, batched = tell_delay(ctrl, jnp.asarray(dd.ravel(), jnp.float32)), True
        if law is not None and law.told == "delay_alpha":
            ctrl = ctrl.replace(settings=ctrl.settings.replace(alpha0=jnp.asarray(aa.ravel(), jnp.float32)))
        t0 = time.perf_counter()
        res = run_batch(ctrl, envs, [0] * len(envs), eval_config, record=every > 0, batch_controller=batched,
                        chunk_size=chunk, metrics=MAP_METRICS, every=every)
        out[name] = {k: np.asarray(res.metrics[k]).reshape(dd.shape) for k in ROBUST_METRICS}
        step = np.asarray(res.final.diverged_step).reshape(dd.shape)
        out[name]["diverged_step"] = step
        out[name]["diverged_at_s"] = np.where(out[name]["diverged"], step * eval_config.dt, np.inf)
        out[name]["final_rho_spatial_std"] = VEH_PER_KM * np.std(np.asarray(res.final.rho), axis=-1).reshape(dd.shape)
        out[name]["final_rho_offset"] = VEH_PER_KM * (np.mean(np.asarray(res.final.rho), axis=-1).reshape(dd.shape)
                                                      - own_rho)
        out[name]["late_max_rho_spatial_std"] = np.asarray(res.metrics["late_max_rho_std"]).reshape(dd.shape)
        out[name].update(paper_column(res, n_paper, every, out[name]))
        log(f"  robustness {name:<13s} {len(envs):3d} envs x {eval_config.n_steps} steps"
            f"  {time.perf_counter() - t0:6.1f} s | {_eta(len(names) - i - 1, i + 1, t_start)}")
    return out


