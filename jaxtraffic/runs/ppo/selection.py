"""Validation suite for PPO checkpoints: a few initial conditions x plant delays, long horizon.

Each member's deterministic policy (``control.gain_policy.policy_controller``) is rolled out on every scenario
of the suite (the cosine initial conditions ``ics`` = (amplitude veh/km, wavenumber, phase rad) x
the plant delays ``delays`` s; alpha and the rest as the training plant, no noise) for ``steps``
steps, in one batched ``simulate_batch``. The reference is ``backstepping`` assuming the nominal
delay on the same scenarios. Per scenario i (rho L2 at half the horizon and at its end, J_comfort
over the whole horizon):

    s_i = max(L2_half_i / L2_half_ref_i, J_i / (j_slack * J_ref_i))   (scenarios at the nominal delay)
    s_i = 0                                                             (the other delays)

and ``score = max_i s_i`` (the worst case; smaller is better), set to ``BAD`` when any rollout
diverged or its density L2 at the end is not below the value at half the horizon (a slow mode
that grows or does not decay). So the nominal delay measures performance and the other delays
only stability (backstepping assuming the nominal delay is not a fair bar there: at 3 s it settles
twice as fast as at 4 s). ``score <= 1`` means: at the nominal delay the density at half the
horizon is below backstepping's and J_comfort within ``j_slack`` of its, and at every delay the
plant does not diverge and is still converging.

A run trained on the train split (``EnvConfig.train_split``) is validated on that split instead
(``make_split_suite``): its own training scenarios, scored by the held-out comparison's measure, so that nothing of
its selection reads the paper's wave (docs/model.md section 20).

The trainer's checkpoint selection (below): ``scores`` of one evaluation per member, and the best
checkpoint kept per member (``BestCheckpoints``; saved as best.msgpack by
``runs.checkpoint``). Not to be confused with ``runs.config.checks``, which checks config values.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, cast

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxtraffic.compare import stats
from jaxtraffic.compare.protocol import measure, steps_of
from jaxtraffic.compare.scenarios import ScenarioDistribution, sample
from jaxtraffic.control.adapter import ControllerGrid, adapt, baseline_grid
from jaxtraffic.control.base import tell_delay
from jaxtraffic.control.baselines import backstepping
from jaxtraffic.control.noise import sensor_noise as seen_through
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM
from jaxtraffic.sim.options import Record
from jaxtraffic.sim.rollout import simulate_batch

BAD = 1e6
SUITE_METRICS = ("final_rho_L2", "J_comfort", "diverged")  # what the suite reads of each rollout
DEFAULT_ICS = ((10.0, 4.0, 0.0), (10.0, 4.0, math.pi))  # the paper's, and the same shifted by half a wave


def scenarios(nominal, delays, ics):
    """(plants stacked over scenarios, rho0 (S, n), v0 (S, n), labels)."""
    rows = [(d, ic) for ic in ics for d in delays]
    plant = nominal.replace(alpha_noise=0.0)
    init = [paper_initial_condition(plant, a / VEH_PER_KM, k, ph) for _, (a, k, ph) in rows]
    rho0 = jnp.stack([r for r, _ in init])
    v0 = jnp.stack([v for _, v in init])
    plants = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, float), (len(rows),)), plant)
    plants = plants.replace(delay=jnp.asarray([d for d, _ in rows], float))
    labels = [f"D={d:g} amp={a:g} veh/km k={k:g} phase={ph:.2f}" for d, (a, k, ph) in rows]
    return plants, rho0, v0, labels


def _half_and_end(res):
    """(rho L2 at half the horizon, at the end, J_comfort, diverged) of a batched rollout."""
    return res.trajectory.rho_L2[:, 1], res.metrics["final_rho_L2"], res.metrics["J_comfort"], res.metrics["diverged"]


class Suite(Protocol):
    """What ``make_suite`` (``make_split_suite``) returns: ``suite(controller, n_members)`` scores members;
    ``suite.reference`` holds backstepping's numbers on the suite, ``suite.scenarios`` describes them."""

    reference: dict[str, Any]
    scenarios: dict[str, Any]  # what the suite's scenarios are (for the run's summary)
    measure: str  # what its score is, in words

    def __call__(self, controller: Any, n_members: int) -> dict: ...


def make_suite(nominal, steps: int, delays, ics=DEFAULT_ICS, j_slack: float = 1.2, plant=None) -> Suite:
    """``suite(controller, n_members) -> dict`` of numpy arrays: ``score`` (members,) and the
    per-scenario ``rho_L2_half``, ``rho_L2_end`` (veh/km), ``J_comfort``, ``ratio`` (members, S).
    ``controller``: a policy controller on the grid of ``nominal`` whose settings carry a leading member
    axis. ``plant``: the discretisation the suite runs on (n_points, scheme, substeps; default the
    nominal's), every controller acting on its own grid (``control.adapter``; backstepping on the
    paper's, ``baseline_grid``): the training grid need not be the one the policy is judged on."""
    if steps % 2:
        raise ValueError("the validation horizon needs an even number of steps")
    judge = nominal if plant is None else nominal.replace(n_points=plant.n_points, scheme=plant.scheme,
                                                          substeps=plant.substeps)
    plants, rho0, v0, labels = scenarios(judge, delays, ics)
    n_s = len(labels)
    nominal_delay = np.isclose(np.asarray(plants.delay), float(nominal.delay))
    grid = ControllerGrid.of(nominal)
    ref = simulate_batch(plants, adapt(backstepping(float(nominal.delay)), baseline_grid(judge), judge),
                         n_steps=steps, rho0=rho0, v0=v0, nominal=judge, record=Record(every=steps // 2),
                         metrics=SUITE_METRICS)
    ref_half, ref_end, ref_j, ref_div = (np.asarray(x) for x in _half_and_end(ref))
    if ref_div.any():
        raise ValueError("backstepping diverged on the validation suite")

    def suite(controller, n_members: int) -> dict:
        ctrl = adapt(jax.tree.map(lambda x: jnp.repeat(x, n_s, axis=0), controller), grid, judge)  # member-major
        tile = lambda x: jnp.tile(x, (n_members,) + (1,) * (x.ndim - 1))  # noqa: E731
        res = simulate_batch(jax.tree.map(tile, plants), ctrl, n_steps=steps, rho0=tile(rho0), v0=tile(v0),
                             nominal=judge, record=Record(every=steps // 2), batch_controller=True,
                             metrics=SUITE_METRICS)
        half, end, jc, div = (np.asarray(x).reshape(n_members, n_s) for x in _half_and_end(res))
        with np.errstate(invalid="ignore", over="ignore"):
            ratio = np.maximum(half / ref_half, jc / (j_slack * ref_j))
            bad = div | ~(end < half) | ~np.isfinite(ratio)
        ratio = np.where(bad, BAD, np.where(nominal_delay, ratio, 0.0))
        return {"score": ratio.max(axis=1), "ratio": ratio, "rho_L2_half": half, "rho_L2_end": end,
                "J_comfort": jc, "labels": labels}

    out = cast(Suite, suite)  # a function with attributes: the Protocol's members
    out.reference = {"rho_L2_half": ref_half, "rho_L2_end": ref_end, "J_comfort": ref_j,
                     "labels": labels}
    out.scenarios = {"delays": list(delays)}
    out.measure = "the worst ratio to backstepping over the suite"
    return out


def make_split_suite(nominal, horizon_s: float, n_train: int, plant=None,
                     sensor_noise: tuple[float, float] = (0.0, 0.0)) -> Suite:
    """The suite of a run trained on the train split (``EnvConfig.train_split`` = ``n_train``): its own
    ``n_train`` training scenarios (``compare.scenarios.sample``, seed 0, as ``EpisodePool.train_split`` draws
    them; on ``plant``'s grid, default the nominal's) over ``horizon_s`` s, scored by the held-out comparison's
    measure and nothing of the paper's wave: per member, the mean over the scenarios of the time-averaged density
    L2 (veh/km, ``compare.protocol.measure``; capped at ``stats.L2_CAP``, a diverged scenario at the cap), as a
    ratio to backstepping's (told each scenario's D, on the paper's grid) on the same scenarios. The
    ``mean_l2`` objective of the CEM laws and the tuned baselines, as a ratio (``score`` <= 1: as good as
    backstepping); ``ratio`` (members, S): the per-scenario capped ratios. ``sensor_noise`` (``EnvConfig.
    train_sensor_noise``): every law, backstepping too, sees each scenario through its split's noise level and key
    (``control.noise.sensor_noise``), as the comparison's ``--sensor-noise`` has it."""
    judge = nominal if plant is None else nominal.replace(n_points=plant.n_points, scheme=plant.scheme,
                                                          substeps=plant.substeps)
    noise_range = (float(sensor_noise[0]), float(sensor_noise[1]))
    scen = sample(ScenarioDistribution(sensor_noise_range=noise_range), "train", n_train, 0,
                  base=judge.replace(alpha_noise=0.0))
    n_steps, every = steps_of(horizon_s, float(judge.dt))
    n_s, plants, noisy = len(scen), scen.plants, sensor_noise[1] > 0
    levels, keys = scen.noise_levels(), scen.keys()

    def run(plants, ctrl, grid, reps: int) -> dict:  # ``reps`` copies of the scenarios, the law batched over them
        tile = lambda x: np.tile(x, (reps,) + (1,) * (np.ndim(x) - 1))  # noqa: E731
        if noisy:  # on the law's own grid, before the adapter (as compare.protocol)
            ctrl = seen_through(ctrl, jnp.asarray(tile(levels), jnp.float32), batched=True)
        return measure(jax.tree.map(tile, plants), adapt(ctrl, grid, judge), tile(scen.rho0), tile(scen.v0), judge,
                       n_steps, every, batch_controller=True, keys=jnp.asarray(tile(keys)) if noisy else None)

    ref = stats.capped(run(plants, tell_delay(backstepping(), jnp.asarray(plants.delay)), baseline_grid(judge),
                           1)["mean_rho_L2"])
    grid = ControllerGrid.of(nominal)

    def suite(controller, n_members: int) -> dict:
        ctrl = jax.tree.map(lambda x: jnp.repeat(x, n_s, axis=0), controller)  # member-major
        per = run(plants, ctrl, grid, n_members)
        mean = stats.capped(per["mean_rho_L2"]).reshape(n_members, n_s)
        return {"score": mean.mean(axis=1) / ref.mean(), "ratio": mean / ref, "mean_rho_L2": mean}

    out = cast(Suite, suite)
    out.reference = {"mean_rho_L2": ref, "law": "backstepping told each scenario's D"}
    out.scenarios = {"train_split": n_train, "seed": 0, "horizon_s": n_steps * float(judge.dt),
                     **({"sensor_noise": list(sensor_noise)} if noisy else {})}
    out.measure = f"the mean time-averaged density L2 over {n_train} train-split scenarios as a ratio to backstepping's"
    return out


# ----------------------------------------------------------------------------- checkpoint selection
UNVALIDATED = 1e7  # score of a checkpoint that failed the cheap rule (not validated); BAD: validated and rejected
# (kept numbers: the selection orders every member by one score; ``Validation.of`` names what a score says)


def validation_delays(env_params) -> tuple[float, ...]:
    """Plant delays of the suite: the ends of the training range and the nominal delay (s)."""
    return tuple(sorted({round(float(x), 6) for x in (env_params.delay_min, env_params.traffic.delay,
                                                      env_params.delay_max)}))


def scores(reward: np.ndarray, candidate: np.ndarray, suite, controller, rank_all: bool = False) -> np.ndarray:
    """Per-member score of one evaluation (lower is better): the suite's score of the ``candidate``
    members (``controller()``: their policy controller with a leading member axis, built only if
    needed); the others rank below every candidate, by evaluation reward ``reward`` (the paper's wave), or with
    ``rank_all`` (a run trained on the train split: nothing of its selection may read the paper's wave) by their
    own suite score. Without a suite (``suite`` None) the evaluation reward ranks the candidates too."""
    score = UNVALIDATED - np.where(np.isfinite(reward), np.maximum(reward, -1e6), -1e6)
    if suite is None:
        return np.where(candidate, -reward, score)
    if rank_all:
        suite_score = suite(controller(), len(reward))["score"]
        return np.where(candidate, suite_score, UNVALIDATED + np.minimum(suite_score, BAD))
    if candidate.any():
        score = np.where(candidate, suite(controller(), len(reward))["score"], score)
    return score


@dataclass(frozen=True)
class BestCheckpoints:
    """Per member (leading axis M): the best-scoring policy so far (flax ``params``, observation ``mean`` and
    ``var``), its ``score`` (``scores``; inf: none yet) and the ``env_steps`` at which it was reached."""

    params: Any
    mean: np.ndarray
    var: np.ndarray
    score: np.ndarray
    env_steps: np.ndarray

    @classmethod
    def empty(cls, params, mean, var) -> BestCheckpoints:
        """The record of members that have no best checkpoint yet (score inf); the arrays give the structure."""
        n = np.shape(mean)[0]
        return cls(params=params, mean=np.asarray(mean), var=np.asarray(var), score=np.full((n,), np.inf),
                   env_steps=np.zeros((n,), np.int64))

    def update(self, score: np.ndarray, env_steps: int, policy: Callable[[], tuple]) -> BestCheckpoints:
        """Keep, per member, the checkpoint with the lowest score; ``policy()``: the current (params, mean, var)
        with a leading member axis, read only if a member improved."""
        better = score < self.score
        if not better.any():
            return self
        params, mean, var = policy()

        def pick(old, new):
            mask = better.reshape((-1,) + (1,) * (np.ndim(new) - 1))
            return np.where(mask, np.asarray(new), np.asarray(old))

        return BestCheckpoints(params=jax.tree.map(pick, self.params, params), mean=pick(self.mean, mean),
                               var=pick(self.var, var), score=np.where(better, score, self.score),
                               env_steps=np.where(better, env_steps, self.env_steps))

    def state_dict(self) -> dict:
        """What best.msgpack holds (``runs.checkpoint.save_best``)."""
        return {"params": serialization.to_state_dict(jax.device_get(self.params)),
                **{k: np.asarray(getattr(self, k)) for k in ("mean", "var", "score", "env_steps")}}

    def restored(self, state: dict) -> BestCheckpoints:
        """This record's structure filled with a loaded best.msgpack (``runs.checkpoint.load_best``)."""
        return BestCheckpoints(params=serialization.from_state_dict(self.params, state["params"]),
                               **{k: np.asarray(state[k]) for k in ("mean", "var", "score", "env_steps")})


class Validation(enum.Enum):
    """What a checkpoint's score says (the value: its text on a progress line; ``message``: in words)."""

    SCORED = "scored"
    REJECTED = "bad"
    NOT_VALIDATED = "-"

    @classmethod
    def of(cls, score: float) -> Validation:
        """The status of one member's ``score`` (``scores``: UNVALIDATED less a reward, BAD, or the suite's)."""
        return cls.NOT_VALIDATED if score >= (BAD + UNVALIDATED) / 2 else cls.REJECTED if score >= BAD else cls.SCORED

    @property
    def message(self) -> str:
        return {Validation.SCORED: "validated; the score is the suite's (<= 1: as good as backstepping)",
                Validation.REJECTED: "validated and rejected: a rollout diverged or stopped converging",
                Validation.NOT_VALIDATED: "not validated: the evaluation's rule failed (ranked below every validated "
                                          "one)"}[self]


def format_scores(score: np.ndarray) -> str:
    """Scores for a progress line: the score, or the status's text when it is not a score ("-", "bad")."""
    return ",".join(f"{x:.2f}" if (v := Validation.of(x)) is Validation.SCORED else v.value for x in np.asarray(score))


# ----------------------------------------------------------------------------- the run's closing line
def best_text(score: float, member: int, env_steps: int, measure: str | None, rank_all: bool = False) -> str:
    """The best checkpoint in words for the run's closing line: its score and what it ``measure``s (the suite's
    ``measure``; None: no validation suite ran), or that no checkpoint was scored and how the kept one was ranked
    (``rank_all``: as ``scores``'s); never the ranking's internal numbers."""
    validated = measure is not None
    where = f"member {member} at {env_steps} env steps"
    if not math.isfinite(score):
        return "no best checkpoint kept"
    status = Validation.of(score)
    if status is Validation.SCORED and validated:
        return (f"best checkpoint: {where}, validation score {score:.3g} ({measure}, dimensionless; <= 1: as good "
                "as backstepping)")
    if status is Validation.SCORED:  # no suite: the score is the evaluation reward, negated
        return f"best checkpoint: {where}, evaluation reward {-score:.4g} (dimensionless)"
    if status is Validation.REJECTED:
        return (f"no scored checkpoint (every validated one was rejected: a rollout diverged or stopped converging); "
                f"the policy kept: {where}")
    return (f"no scored checkpoint (none met the evaluation's conditions of the stop rule); the policy kept: {where}, "
            + (f"the best by {measure} among them" if rank_all and validated else "the highest evaluation reward"))


def rule_text(run: Any, ev: dict, certified: np.ndarray | None, score: np.ndarray | None,
              paper_rule: bool = True) -> str:
    """Per member, which conditions of the stop rule its evaluation ``ev`` (``final_reward``, ``diverged``,
    ``wave_speed``) met and failed, with the values. ``run``: the run's ``RunConfig``; ``certified`` and ``score``
    (``scores``): of the same evaluation, None when unknown (not evaluated in this session). The certificate and
    the validation are checked only for members meeting the conditions before them. ``paper_rule`` False: the
    evaluation reward is not a condition (a run validated on the train split, ``make_split_suite``)."""
    lines = []
    for i, (r, div, s) in enumerate(zip(*(np.asarray(ev[k]).tolist() for k in ("final_reward", "diverged",
                                                                               "wave_speed")), strict=True)):
        ok: bool | None = (r >= run.target_reward and not div) or not paper_rule  # None: unknown in this session
        parts = ["reward target not a condition (validated on the train split)" if not paper_rule else
                 "reward target not met (the evaluation diverged)" if div else
                 f"reward target {_met(ok)} (eval reward {r:.4g} {'>=' if ok else '<'} {run.target_reward:g}, "
                 "dimensionless)"]
        if run.min_wave_speed is not None:
            fast = s >= run.min_wave_speed
            ok = ok and fast
            parts.append(f"wave speed {_met(fast)} ({s:+.2f} m/s {'>=' if fast else '<'} {run.min_wave_speed:g} m/s)")
        if run.require_certificate:
            cert = None if certified is None or not ok else bool(certified[i])
            parts.append(f"certificate {'not checked' if not ok else _met(cert)}")
            ok = ok and cert
        if run.val_horizon_s > 0:
            x = None if score is None or not ok else float(score[i])
            scored = x is not None and Validation.of(x) is Validation.SCORED
            parts.append("validation " + ("not run" if ok is False else _met(None) if x is None else
                                          f"{_met(x <= run.val_target)} (score {x:.3g} "
                                          f"{'<=' if x <= run.val_target else '>'} {run.val_target:g})" if scored
                                          else "not met (rejected: a rollout diverged or stopped converging)"))
        lines.append(f"member {i}: " + ", ".join(parts))
    return "; ".join(lines)


def _met(ok: bool | None) -> str:
    return "unknown (not evaluated in this session)" if ok is None else "met" if ok else "not met"
