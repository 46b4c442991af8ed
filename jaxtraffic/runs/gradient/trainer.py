"""The gradient and CEM trainers' part of a training run (``runs.loop.run_training`` does the rest).

A chunk is ``steps_per_chunk`` Adam steps of ``objective.make_train`` (or CEM generations of ``cem.make_train``,
``grad_method = "cem"``). The run directory has the same files as a PPO run (config.json with the same config
tree, checkpoint.msgpack, learning_curve.csv/.png, summary.json) and loads with ``runs.load_policy``. After every
chunk the deterministic controller is evaluated on the paper's initial condition with the nominal plant
(``eval_horizon_s``) next to the delay-compensated baseline ``backstepping(delay)``; the summary records when it
first met the paper's stop rule and when it first beat backstepping on both final density L2 and J_comfort. The
checkpoint is written after every chunk; ``resume`` continues from it exactly (training is deterministic).

Multi-process runs (``jaxtraffic.platform.distributed``): the scenarios of every Adam step are split over every device
of every process (``objective.make_train``), the stop and wall-budget decisions are process 0's and a signal to
any process stops all of them after the same chunk (``runs.session.agree_stop``), and only process 0 prints and
writes. A checkpoint holds no per-device state, so it resumes on any number of processes and devices (to float
rounding: the scenario split changes the sums' order).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.control.base import Controller
from jaxtraffic.control.baselines import backstepping
from jaxtraffic.control.gain_policy import equilibrium_gains, feature_size
from jaxtraffic.control.networks import actor_critic_size
from jaxtraffic.io.files import write_json
from jaxtraffic.learn.gradient import cem, objective
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.learn.gradient.policies import POLICIES
from jaxtraffic.model.linear import gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, config_json
from jaxtraffic.runs.config.checks import CARRY_COPIES, NETWORK_COPIES, refuse_memory
from jaxtraffic.runs.gradient.policy import gradient_setup, own_grid_controller
from jaxtraffic.runs.loop import Clock, Progress, prepare, run_training, summary_base
from jaxtraffic.runs.policy import policy_certificate
from jaxtraffic.runs.session import check_finite, check_total, eta_text, fmt_time
from jaxtraffic.sim.metrics import REWARD_TARGET
from jaxtraffic.sim.rollout import simulate
from jaxtraffic.sim.units import INDEX_UNITS

__all__ = ["CURVE_FIELDS", "beats", "evaluation", "policy_evaluation", "train_gradient"]

ALGO = "gradient"
# control.stability certifies the three-gain law (a Fourier multiplier of the observed state); the residual policy
# adds it to adaptive backstepping, whose predictor and estimator the certificate does not model
RESIDUAL_CERTIFICATE = {"applies": False, "stable": None, "reason": "control.stability certifies the three-gain law "
                        "alone; the residual law is adaptive backstepping (a predictor over the pending inputs and "
                        "an online estimate of alpha) plus a gain-law correction, which it does not model"}
MILESTONES = ("paper_rule", "beat_backstepping")


def evaluation(ctrl: Controller, plant: TrafficParams, n_steps: int, gains: Any | None,
               own: tuple[Controller, TrafficParams] | None = None) -> dict:
    """Deterministic rollout metrics of ``ctrl`` on the paper's initial condition, plus the gains it
    settles to at the equilibrium (``gains`` if given, else those of ``own`` = (the controller on its
    own grid, its nominal there)) and the closed loop's wave speed there (m/s)."""
    res = simulate(plant, ctrl, n_steps=n_steps)
    out = {k: float(v) for k, v in res.metrics.items()}
    if gains is None:
        assert own is not None, "evaluation: give gains or own"
        g = equilibrium_gains(*own)
    else:
        g = jnp.asarray(gains)
    out["equilibrium_gains"] = np.asarray(g).tolist()
    out["wave_speed"] = float(gain_law_wave_speed(g, linearize(plant)))
    return out


def policy_evaluation(theta: Any, grad_config: GradientConfig, plant: TrafficParams, n_steps: int) -> dict:
    """``evaluation`` of the controller of ``theta`` acting on ``plant``."""
    own = (own_grid_controller(theta, grad_config, plant, plant.delay),
           plant.replace(n_points=grad_config.controller_points or plant.n_points, substeps=1))
    return evaluation(objective.make_controller(theta, grad_config, plant), plant, n_steps,
                      objective.fixed_gains(theta, grad_config, plant.delay), own)


def beats(ev: dict, ref: dict) -> bool:
    """Final density L2 and J_comfort both below the reference's, not diverged."""
    return (not ev["diverged"]) and ev["final_rho_L2"] < ref["final_rho_L2"] and ev["J_comfort"] < ref["J_comfort"]


CURVE_FIELDS = ["update", "env_steps", "wall_s", "objective", "grad_norm", "eval_reward", "eval_J_comfort",
                "eval_rho_L2_veh_km", "eval_wave_speed", "eta1", "eta2", "eta3"]


class GradientTraining:
    """The gradient and CEM trainers' hooks for ``runs.loop`` (``runs.loop.Algorithm``): a chunk is
    ``steps_per_chunk`` Adam steps (CEM generations), evaluated next to backstepping; a checkpoint after
    every chunk."""

    unit = "Adam steps"
    curve_fields = CURVE_FIELDS
    checkpoint_every = 1

    def __init__(self, config: TrainConfig, grad_config: GradientConfig, plant: TrafficParams) -> None:
        self.config, self.grad_config, self.plant = config, grad_config, plant
        self.total = grad_config.grad_steps
        self.curve_title: str | None = f"gradient-based training ({grad_config.policy})"
        self.init, self.train_chunk = (cem.make_train if grad_config.grad_method == "cem" else objective.make_train)(
            grad_config, plant)
        self.eval_steps = max(1, round(config.run.eval_horizon_s / config.plant.dt))
        self.ev: dict = {}

    def start(self, saved: tuple[Any, dict] | None, say: Callable[..., None]) -> str:
        config, grad_config, plant = self.config, self.grad_config, self.plant
        self.state = self.init(jax.random.PRNGKey(config.run.seed))
        self.progress = Progress("updates", MILESTONES)
        if saved is not None:
            self.progress = Progress.from_meta(saved[1], "updates", MILESTONES)
            # every shape checked (another --init-gains / --policy / network): before anything is rewritten
            self.state = ckpt.restore_runner(self.state, saved[0], Path(config.run.out_dir) / ckpt.CHECKPOINT)
        self.ref = evaluation(adapt(backstepping(config.plant.delay), baseline_grid(plant), plant), plant,
                              self.eval_steps, gains=jnp.zeros(3))
        n_steps = objective.horizon_steps(grad_config, config.plant.dt)
        cem_run = grad_config.grad_method == "cem"
        self.steps_per_update = grad_config.n_scenarios * n_steps * (grad_config.cem_population if cem_run else 1)
        step = f"CEM generation of {grad_config.cem_population} candidates" if cem_run else "Adam step"
        return (f"training by {'CEM' if cem_run else 'gradient'} ({grad_config.policy}): {grad_config.n_scenarios} "
                f"scenarios x {n_steps} steps per {step}, {grad_config.steps_per_chunk} steps/chunk, plant D = "
                f"{config.plant.delay:g} s; backstepping reference: rho L2 {self.ref['final_rho_L2']:.3f} "
                f"veh/km, J_comfort {self.ref['J_comfort']:.4g} {INDEX_UNITS['J_comfort']}")

    def chunk(self, clock: Clock) -> tuple[dict, str]:
        prog, grad_config = self.progress, self.grad_config
        self.state, m = self.train_chunk(self.state)
        jax.block_until_ready(m)
        check_finite("the objective, gradient or parameters", {"objective": m["objective"], "grad_norm":
                                                               m["grad_norm"], "theta": self.state.theta},
                     Path(self.config.run.out_dir), f"{prog.updates} Adam steps")
        ev = self.ev = policy_evaluation(self.state.theta, grad_config, self.plant, self.eval_steps)
        t_prev = prog.rows[-1]["wall_s"] if prog.rows else prog.wall_s
        prog.updates += grad_config.steps_per_chunk
        prog.env_steps += grad_config.steps_per_chunk * self.steps_per_update
        prog.wall_s = clock.wall()
        g = ev["equilibrium_gains"]
        row = {"update": prog.updates, "env_steps": prog.env_steps, "wall_s": round(prog.wall_s, 3),
               "objective": float(m["objective"][-1]), "grad_norm": float(m["grad_norm"][-1]),
               "eval_reward": ev["final_reward"], "eval_J_comfort": ev["J_comfort"],
               "eval_rho_L2_veh_km": ev["final_rho_L2"], "eval_wave_speed": ev["wave_speed"],
               "eta1": g[0], "eta2": g[1], "eta3": g[2]}
        prog.rows.append(row)
        prog.mark("paper_rule", (not ev["diverged"]) and ev["final_reward"] >= REWARD_TARGET)
        better = beats(ev, self.ref)
        prog.mark("beat_backstepping", better)
        spread = "|grad|" if grad_config.grad_method == "adam" else "spread"
        line = (f"[update {prog.updates:>4d}] objective {row['objective']:.4f} | {spread} {row['grad_norm']:.3g} | "
                f"eval reward {row['eval_reward']:.4f} | rho L2 {row['eval_rho_L2_veh_km']:.3f} veh/km | "
                f"J_comfort {row['eval_J_comfort']:.4g} {INDEX_UNITS['J_comfort']} | "
                f"gains ({g[0]:+.2f}, {g[1]:+.2f}, {g[2]:+.2f}) | "
                f"{fmt_time(prog.wall_s)} ({prog.wall_s - t_prev:.1f} s/chunk) | "
                f"{eta_text(self.total - prog.updates, clock.rate(prog.updates))}"
                + (" | beats backstepping" if better else ""))
        return row, line

    def snapshot(self):
        return self.state

    def save(self, state, meta: dict, run_dir: Path, writer: bool) -> None:
        if writer:
            ckpt.save_checkpoint(run_dir, state, meta)

    def saved_best(self, run_dir: Path, writer: bool) -> None:
        """Nothing: a gradient run keeps no best checkpoint (its checkpoint is written after every chunk)."""

    def finish(self, interrupted: bool, run_dir: Path, writer: bool) -> str:
        prog, grad_config, config = self.progress, self.grad_config, self.config
        ev = self.ev or policy_evaluation(self.state.theta, grad_config, self.plant, self.eval_steps)
        summary = {**summary_base(prog, interrupted, config.run.eval_horizon_s), "algo": ALGO,
                   "policy": grad_config.policy, "updates": prog.updates, "final_eval": ev,
                   "backstepping_eval": self.ref, "stop_rule_reached": prog.seconds_to("paper_rule") is not None}
        summary.update(POLICIES[grad_config.policy].summary(jax.device_get(self.state.theta), grad_config))
        own = own_grid_controller(jax.device_get(self.state.theta), grad_config, self.plant, self.plant.delay)
        if grad_config.policy == "residual":  # (the certificate covers the three-gain law only)
            summary["certificate"] = RESIDUAL_CERTIFICATE
        else:
            summary["certificate"] = policy_certificate(own, config)
        if writer:
            write_json(run_dir / ckpt.SUMMARY, summary)
        beat = prog.seconds_to("beat_backstepping")
        steps = "Adam steps" if grad_config.grad_method == "adam" else "CEM generations"
        return (f"done: {prog.updates} {steps} in {prog.wall_s:.1f} s; final rho L2 {ev['final_rho_L2']:.3f} "
                f"veh/km, J_comfort {ev['J_comfort']:.4g} {INDEX_UNITS['J_comfort']}; "
                + (f"first beat backstepping after {beat:.1f} s" if beat is not None else "never beat backstepping")
                + f"; outputs in {run_dir}")


def memory_estimate(grad_config: GradientConfig, plant: TrafficParams) -> dict[str, float]:
    """The bytes one gradient (or CEM) step holds (float32), by what holds them: every scenario's (and CEM
    candidate's) plant state (fields, delay buffer; ``CARRY_COPIES``), stored once per recording chunk for the
    backward pass (Adam) plus the chunk recomputed, or once (CEM: no backward pass); and the policy's parameters
    (``NETWORK_COPIES`` per candidate)."""
    n_steps = objective.horizon_steps(grad_config, plant.dt)
    every = grad_config.record_every
    cem_run = grad_config.grad_method == "cem"
    batch = grad_config.n_scenarios * (grad_config.cem_population if cem_run else 1)
    state = (plant.max_delay_steps + 6) * plant.n_points
    size = actor_critic_size(feature_size(plant.n_points), grad_config.hidden) if grad_config.policy == "network" else 3
    return {"rollouts": 4.0 * CARRY_COPIES * batch * state * (1 if cem_run else n_steps // every + every),
            "networks": 4.0 * NETWORK_COPIES * (grad_config.cem_population if cem_run else 1) * size}


def check_memory(grad_config: GradientConfig, plant: TrafficParams, have: float | None = None) -> None:
    """The gradient trainer's rollouts must fit this machine's memory (``have`` bytes; default: the physical
    memory); the same rule as PPO's (``runs.config.checks.refuse_memory``)."""
    refuse_memory(memory_estimate(grad_config, plant), have, "n_scenarios", grad_config.n_scenarios,
                  f"(--train-delays x initial states) on {plant.n_points} points over "
                  f"{objective.horizon_steps(grad_config, plant.dt)} steps with max_delay_steps = "
                  f"{plant.max_delay_steps}", "use fewer scenarios, points or a shorter --train-horizon-s")


def train_gradient(config: TrainConfig, callbacks: Sequence[Callable[[dict], None]] = ()) -> Path:
    """Train (or resume) by gradient or CEM and return the run directory. Uses ``config.grad`` (with its own gain
    bound, ``grad_gain_max``), ``config.plant`` (the nominal plant), ``config.env.gain_filter``,
    ``config.ppo.hidden`` (network policy) and the run-control fields of ``config.run``; on resume, the saved
    config with the new ``RUN_CONTROL`` fields and ``grad_steps``. ``callbacks``: each learning-curve row."""
    config, run_dir, saved = prepare(config)
    grad_config, plant = gradient_setup(config)  # validates: fail before creating the run directory
    objective.check_scenarios(grad_config, plant)
    if grad_config.grad_steps % grad_config.steps_per_chunk:  # a chunk is one compiled program of steps_per_chunk steps
        raise ValueError(f"grad_steps = {grad_config.grad_steps}: must be a multiple of steps_per_chunk "
                         f"({grad_config.steps_per_chunk}), the Adam steps of one compiled chunk")
    check_memory(grad_config, plant)
    if saved is not None:
        check_total(saved[1], "updates", grad_config.grad_steps, "grad_steps", run_dir / ckpt.CHECKPOINT)
    return run_training(config, run_dir, saved, lambda: GradientTraining(config, grad_config, plant),
                        lambda: config_json(config, jax_version=jax.__version__), callbacks,
                        "jaxtraffic.train_gradient")
