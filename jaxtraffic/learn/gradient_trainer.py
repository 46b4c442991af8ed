"""Training loop around ``gradient.make_train`` (or ``cem.make_train``, ``method = "cem"``: its generations in
place of the Adam steps): chunks, evaluation, checkpoints, outputs.

The run directory has the same files as a PPO run (config.json with the same config tree,
checkpoint.msgpack, learning_curve.csv/.png, summary.json) and loads with ``learn.load_policy``. After every chunk
of Adam steps the deterministic controller is evaluated on the paper's initial condition with
the nominal plant (``eval_horizon_s``) next to the delay-compensated baseline
``backstepping(delay)``; the summary records when it first met the paper's stop rule and when
it first beat backstepping on both final density L2 and J_comfort. Ctrl-C keeps the last completed
chunk; ``resume`` continues from it exactly (training is deterministic).

Multi-process runs (``jaxtraffic.distributed``): the scenarios of every Adam step are split over every
device of every process (``gradient.make_train``), the stop and wall-budget decisions are process
0's and a signal to any process stops all of them after the same chunk (``session.agree_stop``), and
only process 0 prints and writes. A checkpoint holds no per-device state, so it resumes on any
number of processes and devices (to float rounding: the scenario split changes the sums' order).
"""

from __future__ import annotations

import contextlib
import signal
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxtraffic import distributed
from jaxtraffic.control.adapter import adapt, baseline_grid
from jaxtraffic.control.base import Controller
from jaxtraffic.control.baselines import backstepping
from jaxtraffic.control.gain_policy import equilibrium_gains
from jaxtraffic.files import write_json
from jaxtraffic.learn import cem
from jaxtraffic.learn import checkpoint as ckpt
from jaxtraffic.learn import gradient as G
from jaxtraffic.learn.config import RUN_CONTROL, TrainConfig, config_json, load_config
from jaxtraffic.learn.curve import plot_learning_curve, write_curve
from jaxtraffic.learn.metrics_writer import TensorBoardWriter
from jaxtraffic.learn.session import (
    StopSignals,
    TrainingInterrupted,
    agree_stop,
    check_finite,
    check_out_dir,
    check_resumable,
    claim_run_dir,
    finish_together,
    fmt_time,
    own_run_dir,
    report_interruption,
)
from jaxtraffic.model.linear import gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.provenance import provenance
from jaxtraffic.sim.metrics import REWARD_TARGET
from jaxtraffic.sim.rollout import simulate

ALGO = "gradient"


def gradient_setup(cfg: TrainConfig) -> tuple[G.GradientConfig, TrafficParams]:
    """The algorithm config and the nominal plant of a ``TrainConfig`` with ``run.algo = "gradient"``."""
    return cfg.grad.gradient_config(cfg.env, cfg.algo.hidden()), cfg.plant.traffic().replace(alpha_noise=0.0)


def load_gradient_policy(run_dir: str | Path, cfg: TrainConfig) -> Controller:
    """The controller saved in a gradient-trained run directory (``cfg``: its ``load_config``), on its own
    grid (``checkpoint.policy_grid``)."""
    gcfg, plant = gradient_setup(cfg)
    state, _ = ckpt.load_checkpoint(run_dir)
    template = G.init_theta(gcfg, plant, jax.random.PRNGKey(0))
    theta = serialization.from_state_dict(template, state["theta"])
    n = gcfg.controller_points or plant.n_points
    return G.own_controller(jax.tree.map(jnp.asarray, theta), gcfg, n, G.ROAD_LENGTH / (n - 1), cfg.plant.delay)


def evaluation(ctrl: Controller, plant: TrafficParams, n_steps: int, gains: Any | None,
               own: tuple[Controller, TrafficParams] | None = None) -> dict:
    """Deterministic rollout metrics of ``ctrl`` on the paper's initial condition, plus the gains it
    settles to at the equilibrium (``gains`` if given, else those of ``own`` = (the controller on its
    own grid, its nominal there)) and the closed loop's wave speed there (m/s)."""
    res = simulate(plant, ctrl, n_steps=n_steps)
    out = {k: float(v) for k, v in res.metrics.items()}
    g = jnp.asarray(gains) if gains is not None else equilibrium_gains(*own)
    out["equilibrium_gains"] = np.asarray(g).tolist()
    out["wave_speed"] = float(gain_law_wave_speed(g, linearize(plant)))
    return out


def policy_evaluation(theta: Any, cfg: G.GradientConfig, plant: TrafficParams, n_steps: int) -> dict:
    """``evaluation`` of the controller of ``theta`` acting on ``plant``."""
    n = cfg.controller_points or plant.n_points
    own = (G.own_controller(theta, cfg, n, G.ROAD_LENGTH / (n - 1), plant.delay),
           plant.replace(n_points=n, substeps=1))
    return evaluation(G.make_controller(theta, cfg, plant), plant, n_steps, G.fixed_gains(theta, cfg, plant.delay),
                      own)


def beats(ev: dict, ref: dict) -> bool:
    """Final density L2 and J_comfort both below the reference's, not diverged."""
    return (not ev["diverged"]) and ev["final_rho_L2"] < ref["final_rho_L2"] and ev["J_comfort"] < ref["J_comfort"]


CURVE_FIELDS = ["update", "env_steps", "wall_s", "objective", "grad_norm", "eval_reward", "eval_J_comfort",
                "eval_rho_L2_veh_km", "eval_wave_speed", "eta1", "eta2", "eta3"]


def train_gradient(tc: TrainConfig) -> Path:
    """Train (or resume) and return the run directory. Uses ``tc.grad`` (with its own gain bound,
    ``grad_gain_max``), ``tc.plant`` (the nominal plant), ``tc.env.gain_filter`` and
    ``tc.algo.network`` (network policy) and the run-control fields of ``tc.run``; on resume, the
    saved config with the new ``RUN_CONTROL`` fields and ``grad_steps``."""
    run_dir = Path(tc.run.out_dir)
    check_out_dir(run_dir)
    if tc.run.resume:
        check_resumable(run_dir)
        flat = tc.flat()
        tc = load_config(run_dir).replace(**{k: flat[k] for k in (*RUN_CONTROL, "grad_steps")})
        ckpt.check_problem(tc, ckpt.load_checkpoint(run_dir)[1].get(ckpt.PROBLEM), run_dir / ckpt.CHECKPOINT)
    claim_run_dir(run_dir, tc.run.resume, tc.run.overwrite)  # refuse another run's directory before compiling
    cfg, plant = gradient_setup(tc)  # validates: fail before creating the run directory
    G.check_scenarios(cfg, plant)
    if cfg.steps % cfg.steps_per_chunk:  # a chunk is one compiled program of steps_per_chunk Adam steps
        raise ValueError(f"grad_steps = {cfg.steps} (--grad-steps): must be a multiple of --steps-per-chunk "
                         f"({cfg.steps_per_chunk}), the Adam steps of one compiled chunk")
    writer = distributed.is_writer()  # process 0 prints and writes; the others only compute
    say = (lambda *a: None) if tc.run.quiet or not writer else (lambda *a: print(*a, flush=True))
    # --tensorboard DIR: the curve's rows as TensorBoard scalars too (needs tensorboardX: checked before compiling)
    board = TensorBoardWriter(tc.run.tensorboard) if tc.run.tensorboard and writer else None
    with own_run_dir(run_dir, tc.run.resume, tc.run.overwrite, writer, say), \
            finish_together("jaxtraffic.train_gradient"), StopSignals(say) as stop, \
            (contextlib.closing(board) if board else contextlib.nullcontext()):
        return _train_gradient(tc, cfg, plant, run_dir, say, stop, writer, board)


def _train_gradient(tc: TrainConfig, cfg: G.GradientConfig, plant: TrafficParams, run_dir: Path, say,
                    stop: StopSignals, writer: bool, board: TensorBoardWriter | None = None) -> Path:
    run = tc.run
    t_start = time.perf_counter()
    init, train_chunk = (cem.make_train if cfg.method == "cem" else G.make_train)(cfg, plant)
    state = init(jax.random.PRNGKey(run.seed))
    meta: dict = {"updates": 0, "env_steps": 0, "wall_s": 0.0, "rows": [], ckpt.PROBLEM: ckpt.problem_of(tc)}
    if run.resume and (run_dir / ckpt.CHECKPOINT).exists():
        saved, saved_meta = ckpt.load_checkpoint(run_dir)  # (its problem was checked by train_gradient)
        meta = {**meta, **saved_meta}
        state = serialization.from_state_dict(state, saved)
        say(f"resumed {run_dir} at update {meta['updates']} ({meta['wall_s']:.1f} s)")
    if writer:  # (on resume: the run-control values this session was given, recorded)
        write_json(run_dir / ckpt.CONFIG, config_json(tc, jax_version=jax.__version__))
    eval_steps = max(1, round(run.eval_horizon_s / tc.plant.dt))
    ref = evaluation(adapt(backstepping(tc.plant.delay), baseline_grid(plant), plant), plant, eval_steps,
                     gains=jnp.zeros(3))
    n_steps = G.horizon_steps(cfg, tc.plant.dt)
    steps_per_update = cfg.n_scenarios * n_steps * (cfg.cem_population if cfg.method == "cem" else 1)
    wall0 = float(meta["wall_s"])
    step = ("Adam step" if cfg.method == "adam" else f"CEM generation of {cfg.cem_population} candidates")
    say(f"training by {'gradient' if cfg.method == 'adam' else 'CEM'} ({cfg.policy}): {cfg.n_scenarios} scenarios x "
        f"{n_steps} steps per {step}, {cfg.steps_per_chunk} steps/chunk, plant D = {tc.plant.delay:g} s; "
        "backstepping reference: "
        f"rho L2 {ref['final_rho_L2'] * 1e3:.3f} veh/km, J_comfort {ref['J_comfort']:.4g}")
    ev, updates_at_start = {}, meta["updates"]
    signum = agree_stop(False, False, stop)[2]
    try:
        while meta["updates"] < cfg.steps and signum is None:
            state, m = train_chunk(state)
            jax.block_until_ready(m)
            check_finite("the objective, gradient or parameters", {"objective": m["objective"], "grad_norm":
                                                                   m["grad_norm"], "theta": state.theta}, run_dir,
                         f"{meta['updates']} Adam steps")
            ev = policy_evaluation(state.theta, cfg, plant, eval_steps)
            t_prev = meta["rows"][-1]["wall_s"] if meta["rows"] else wall0
            meta["updates"] += cfg.steps_per_chunk
            meta["env_steps"] += cfg.steps_per_chunk * steps_per_update
            meta["wall_s"] = wall0 + time.perf_counter() - t_start
            g = ev["equilibrium_gains"]
            row = {"update": meta["updates"], "env_steps": meta["env_steps"], "wall_s": round(meta["wall_s"], 3),
                   "objective": float(m["objective"][-1]), "grad_norm": float(m["grad_norm"][-1]),
                   "eval_reward": ev["final_reward"], "eval_J_comfort": ev["J_comfort"],
                   "eval_rho_L2_veh_km": ev["final_rho_L2"] * 1e3, "eval_wave_speed": ev["wave_speed"],
                   "eta1": g[0], "eta2": g[1], "eta3": g[2]}
            meta["rows"].append(row)
            paper_rule = (not ev["diverged"]) and ev["final_reward"] >= REWARD_TARGET
            for key, hit in (("paper_rule", paper_rule), ("beat_backstepping", beats(ev, ref))):
                if hit and meta.get(f"seconds_to_{key}") is None:
                    meta[f"seconds_to_{key}"] = meta["wall_s"]
                    meta[f"updates_to_{key}"] = meta["updates"]
            spread = "|grad|" if cfg.method == "adam" else "spread"
            say(f"[update {meta['updates']:>4d}] objective {row['objective']:.4f} | {spread} {row['grad_norm']:.3g} | "
                f"eval reward {row['eval_reward']:.4f} | rho L2 {row['eval_rho_L2_veh_km']:.3f} veh/km | "
                f"J_comfort {row['eval_J_comfort']:.4g} | gains ({g[0]:+.2f}, {g[1]:+.2f}, {g[2]:+.2f}) | "
                f"{fmt_time(meta['wall_s'])} ({meta['wall_s'] - t_prev:.1f} s/chunk)"
                + (" | beats backstepping" if beats(ev, ref) else ""))
            if writer:
                ckpt.save_checkpoint(run_dir, state, meta)
                write_curve(run_dir / "learning_curve.csv", meta["rows"], CURVE_FIELDS)
            if board is not None:
                board(row)
            _, over_budget, signum = agree_stop(False, meta["wall_s"] > run.max_wall_s, stop)
            if over_budget:
                say(f"stopping: wall-clock budget {run.max_wall_s:g} s reached")
                break
    except KeyboardInterrupt:  # raised by Python code (StopSignals turns signals into a flag; not agreed)
        signum = signal.SIGINT
    interrupted = signum is not None
    if interrupted and writer:
        msg = report_interruption(signum, run_dir, bool(meta["rows"]), meta["updates"] != updates_at_start,
                                  f"{meta['updates']} Adam steps")
    if writer:
        plot_learning_curve(run_dir / "learning_curve.csv", run_dir / "learning_curve.png",
                            title=f"gradient-based training ({cfg.policy})")
    if not ev:
        ev = policy_evaluation(state.theta, cfg, plant, eval_steps)
    summary = {"provenance": provenance(), "algo": ALGO, "policy": cfg.policy, "updates": meta["updates"],
               "env_steps": meta["env_steps"],
               "wall_s": meta["wall_s"], "interrupted": interrupted, "eval_horizon_s": run.eval_horizon_s,
               "final_eval": ev, "backstepping_eval": ref,
               "stop_rule_reached": meta.get("seconds_to_paper_rule") is not None,
               **{k: meta.get(k) for k in ("seconds_to_paper_rule", "updates_to_paper_rule",
                                           "seconds_to_beat_backstepping", "updates_to_beat_backstepping")}}
    if cfg.policy == "gains":
        summary["gains"] = np.asarray(state.theta).tolist()
    if cfg.policy == "schedule":
        summary["schedule"] = {"knots_s": list(cfg.knots), "gains": np.asarray(state.theta).tolist()}
    n = cfg.controller_points or plant.n_points
    own = G.own_controller(jax.device_get(state.theta), cfg, n, G.ROAD_LENGTH / (n - 1), plant.delay)
    summary["certificate"] = ckpt.policy_certificate(own, tc)
    if writer:
        write_json(run_dir / ckpt.SUMMARY, summary)
    say(f"done: {meta['updates']} {'Adam steps' if cfg.method == 'adam' else 'CEM generations'} in "
        f"{meta['wall_s']:.1f} s; final rho L2 "
        f"{ev['final_rho_L2'] * 1e3:.3f} veh/km, J_comfort {ev['J_comfort']:.4g}; "
        + (f"first beat backstepping after {beat:.1f} s" if (beat := meta.get("seconds_to_beat_backstepping"))
           is not None else "never beat backstepping") + f"; outputs in {run_dir}")
    if interrupted:
        raise TrainingInterrupted(signum, msg if writer else "")
    return run_dir
