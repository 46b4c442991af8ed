"""Training loop around ``ppo.make_train``: chunks, evaluation, stop rule, checkpoints, outputs.

``train(config)`` runs jit-compiled chunks of PPO updates. Between chunks it evaluates the
deterministic policy of every member (seed) on the paper's initial condition (``eval_horizon_s``,
the training plant without randomisation), prints a progress line, appends to ``learning_curve.csv``,
rewrites the checkpoint atomically after a session's first chunk and every ``checkpoint_every``-th
(and at the end and on a signal; the best checkpoints whenever they improve), and applies the stop
rule unless ``keep_going``. A member meets the
rule at an evaluation when (1) the paper's rule holds (evaluation reward, i.e. the reward at the
end of the evaluation rollout, >= ``target_reward``, no divergence); (2) with ``min_wave_speed``
set, the closed loop under the gains its policy settles to at the equilibrium carries density
waves downstream at least that fast (``linear.gain_law_wave_speed``, m/s: a backward wave speed
leaves a slow mode that enters at the outlet and never decays, which the 300 s evaluation reward
hardly sees), and with ``require_certificate`` those gains are certified (``control.stability``: the
delayed, filtered law's linearised closed loop grows at no wavenumber faster than 1e-3/s at the
training delay and alpha); (3) with a validation suite (``val_horizon_s`` > 0, ``learn.validation``), its
validation score is <= ``val_target``. The suite is rolled out only for evaluations that pass (1)
and (2). The run stops when one member has met the rule at ``stop_patience`` consecutive
evaluations (default 1: the suite is strict, and good policies come in windows of one to three
chunks). ``seconds_to_stop_rule`` records the first time it held, ``seconds_to_paper_rule`` the
first time (1) alone held.

Each member's best checkpoint (lowest validation score; checkpoints that fail (1)-(2) rank below
every validated one, by evaluation reward) is kept in ``best.msgpack``; the member with the best
score is ``summary.json``'s ``best_seed`` and the policy ``load_policy`` returns. ``resume`` continues
exactly from the checkpoint, best checkpoints included (and refuses a directory that has none).

Signals: SIGINT (Ctrl-C) and SIGTERM (what a cluster scheduler sends before killing a job) only
set a flag; the loop stops at the next safe point, after the chunk in progress, with a consistent
checkpoint (or says that none exists yet), writes the summary and raises ``TrainingInterrupted``
(``train.py`` exits 130 / 143). A second signal exits at once without saving (the files on disk
are always complete: every write is atomic). Temporary files left by a killed run are removed
when training starts.

Run directory: config.json, checkpoint.msgpack, best.msgpack, learning_curve.csv,
learning_curve.png, summary.json. The curve's evaluation columns are means over members of the
deterministic rollout: eval_reward (the paper's reward at its end, dimensionless; eval_reward_min and
eval_reward_max: the worst and best member's), eval_J_comfort,
eval_rho_L2_veh_km (final density L2 deviation in veh/km; the metrics' ``final_rho_L2`` is in veh/m)
and eval_wave_speed (m/s, see above); val_score and best_val_score are the lowest over members (1e7
and above: not validated, 1e6: rejected).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic import distributed
from jaxtraffic.control.gain_policy import equilibrium_gains, policy_controller
from jaxtraffic.control.stability import certify
from jaxtraffic.files import write_json
from jaxtraffic.learn import checkpoint as ckpt
from jaxtraffic.learn import env as learn_env
from jaxtraffic.learn import members, ppo, validation
from jaxtraffic.learn.config import RUN_CONTROL, TrainConfig, config_json, load_config
from jaxtraffic.learn.curve import CURVE_FIELDS, append_curve, plot_learning_curve, write_curve
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
from jaxtraffic.learn.validate import check_devices, check_initial_amplitudes, check_memory
from jaxtraffic.model.linear import gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.provenance import provenance
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.metrics import VEH_PER_KM
from jaxtraffic.sim.rollout import simulate_batch

__all__ = ["CURVE_FIELDS", "StopSignals", "TrainConfig", "TrainingInterrupted", "build", "check_resumable",
           "config_dict", "make_evaluator", "train"]


def build(s: TrainConfig) -> tuple[ppo.PPOConfig, learn_env.EnvParams]:
    """PPO config and environment parameters from a ``TrainConfig`` (validated)."""
    traffic = s.plant.traffic()
    pl, en = s.plant, s.env
    d_lo, d_hi = en.delay_range or (max(0.0, pl.delay - en.delay_spread), pl.delay + en.delay_spread)
    d_lo, d_hi = (round(d / pl.dt) * pl.dt for d in (d_lo, d_hi))
    a_lo, a_hi = en.alpha_range or (pl.alpha, pl.alpha)
    env_params = learn_env.make_env_params(
        traffic, horizon=max(1, round(en.horizon_s / pl.dt)), gain_max=en.gain_max, amp_min=en.amp_range[0],
        amp_max=en.amp_range[1], wavenumber_min=int(en.wavenumber_range[0]),
        wavenumber_max=int(en.wavenumber_range[1]), phase_max=en.phase_max, delay_min=d_lo, delay_max=d_hi,
        alpha_min=a_lo, alpha_max=a_hi, gain_filter=en.gain_filter, h_rate_weight=en.h_rate_weight,
        wave_weight=en.wave_weight, wave_speed_min=en.wave_speed_min, obs_segments=en.obs_segments,
        diverge_penalty=en.diverge_penalty, filter_sigma=en.filter_sigma)
    algo = dataclasses.asdict(s.algo)
    cfg = ppo.PPOConfig(num_seeds=s.run.seeds, hidden=s.algo.hidden(),
                        **{f.name: algo[f.name] for f in dataclasses.fields(ppo.PPOConfig) if f.name in algo})
    ppo.validate_config(cfg)
    check_devices(s, len(jax.devices()))
    check_memory(s)
    check_initial_amplitudes(s, traffic)
    return cfg, env_params


def config_dict(s: TrainConfig, cfg: ppo.PPOConfig, env_params: learn_env.EnvParams) -> dict:
    """The run's config.json content (``config.config_json``): the config tree, plus the facts of the
    run that the tree does not hold (the episode length in steps, the devices, the jax version)."""
    return config_json(s, horizon_steps=int(env_params.horizon), devices=[str(d) for d in jax.devices()],
                       jax_version=jax.__version__)


def member_controller(cfg: ppo.PPOConfig, env_params: learn_env.EnvParams, params, obs_mean, obs_var):
    """Deterministic policy controller whose parameters carry a leading member (seed) axis."""
    n = obs_mean.shape[0]
    gain_max = jnp.asarray(env_params.gain_max, float)
    return policy_controller(params, obs_mean, obs_var, jnp.broadcast_to(gain_max, (n,) + gain_max.shape),
                             hidden=tuple(cfg.hidden), init_sigma=cfg.init_sigma, gain_filter=env_params.gain_filter,
                             obs_segments=env_params.obs_segments, sigma_nodes=env_params.filter_nodes)


def make_evaluator(cfg: ppo.PPOConfig, env_params: learn_env.EnvParams, eval_steps: int):
    """Deterministic evaluation of every seed's policy on the paper's initial condition.

    Returns ``evaluate(runner) -> dict`` of per-seed metrics (final_reward, J's, ...), plus the
    gains each policy settles to at the equilibrium (``control.gain_policy.equilibrium_gains``) and the closed
    loop's kinematic wave speed under them (``wave_speed``, m/s, ``linear.gain_law_wave_speed``).
    """
    plant = env_params.traffic.replace(alpha_noise=0.0)
    rho0, v0 = paper_initial_condition(plant)
    lm = linearize(plant)

    @jax.jit
    @jax.vmap
    def equilibrium_diagnostics(ctrl):  # one seed's controller
        gains = equilibrium_gains(ctrl, plant)
        return gains, gain_law_wave_speed(gains, lm)

    def evaluate(runner: ppo.Runner) -> dict:
        rep = members.replicated(runner)  # settings with a leading seed axis: one batched rollout
        ctrl = member_controller(cfg, env_params, rep.params, rep.stats.mean, rep.stats.var)
        res = simulate_batch(plant, ctrl, n_steps=eval_steps, rho0=rho0, v0=v0, batch_controller=True)
        out = {k: np.asarray(v) for k, v in res.metrics.items()}
        gains, speed = equilibrium_diagnostics(ctrl)
        out.update(equilibrium_gains=np.asarray(gains), wave_speed=np.asarray(speed))
        return out

    return evaluate


def _maybe_restart(s: TrainConfig, meta: dict, ok: np.ndarray, runner, init, say):
    """Random restarts: re-initialise every member that has not met the stop rule (``ok``) within
    ``run.restart_steps`` env steps of its (re)start, from the key ``fold_in(seed key, restart
    number)``; the best checkpoints are kept. Bookkeeping in ``meta`` (saved with the checkpoint,
    so a resumed run restarts exactly where an uninterrupted one would): ``member_start_steps``,
    ``member_met``, ``restarts`` (one ``{"env_steps", "members"}`` entry per restart)."""
    n = ok.shape[0]
    start = np.asarray(meta.get("member_start_steps", [0] * n))
    met = np.asarray(meta.get("member_met", [False] * n)) | ok
    due = (~met) & (meta["env_steps"] - start >= s.run.restart_steps)
    stopped = meta["stopped"]
    if s.run.restart_steps and not s.run.keep_going:  # process 0's decision on every process (a collective)
        votes = distributed.agree([*due.astype(int), int(stopped)])[0]
        due, stopped = votes[:-1].astype(bool), bool(votes[-1])
    if (not s.run.restart_steps or s.run.keep_going or stopped or meta["env_steps"] >= s.run.total_steps
            or not due.any()):
        meta["member_start_steps"], meta["member_met"] = start.tolist(), met.tolist()
        return runner
    restarts = meta.setdefault("restarts", [])
    restarts.append({"env_steps": meta["env_steps"], "members": np.flatnonzero(due).tolist()})
    fresh = init(jax.random.fold_in(jax.random.PRNGKey(s.run.seed), len(restarts)))
    meta["member_start_steps"] = np.where(due, meta["env_steps"], start).tolist()
    meta["member_met"] = np.where(due, False, met).tolist()
    say(f"restart {len(restarts)}: member(s) {restarts[-1]['members']} re-initialised (stop rule not met within "
        f"{s.run.restart_steps} env steps of their start; best checkpoints kept)")
    return members.restart_members(runner, fresh, due)


def _certified(gains: np.ndarray, candidate: np.ndarray, s: TrainConfig) -> np.ndarray:
    """Per member: whether its equilibrium ``gains`` (shape (M, 3)) are certified (``control.stability``) at
    the training delay and alpha with the law's filter; computed for the ``candidate`` members only."""
    nominal = s.plant.traffic().replace(alpha_noise=0.0)
    return np.array([bool(c) and certify(g, nominal, float(s.plant.delay), s.env.filter_sigma).stable
                     for g, c in zip(np.asarray(gains), np.asarray(candidate), strict=True)])


LOSSES = ("mean_reward", "value_loss", "entropy", "approx_kl")  # a chunk's metrics that must stay finite


def _save(run_dir: Path, runner: ppo.Runner, meta: dict, best: dict, writer: bool) -> None:
    """The checkpoint and the best checkpoints (the runner is gathered on every process: a collective;
    process 0 writes)."""
    host = distributed.to_host(runner)
    if writer:
        ckpt.save_checkpoint(run_dir, host, meta)
        ckpt.save_best(run_dir, best, meta.get(ckpt.PROBLEM))


def _plot_curve(run_dir: Path) -> None:
    plot_learning_curve(run_dir / "learning_curve.csv", run_dir / "learning_curve.png")


def _config_for_resume(s: TrainConfig, run_dir: Path) -> TrainConfig:
    """The run's saved config, with only the run-control fields (``config.RUN_CONTROL``) taken from ``s``."""
    flat = s.flat()
    return load_config(run_dir).replace(**{k: flat[k] for k in RUN_CONTROL})


def train(s: TrainConfig, callbacks: Sequence[Callable[[dict], None]] = ()) -> Path:
    """Train (or resume) and return the run directory. Raises ``TrainingInterrupted`` after SIGINT or
    SIGTERM (the checkpoint of the last completed chunk is on disk).

    ``callbacks``: callables given each learning-curve row (a dict with the ``CURVE_FIELDS``) as
    soon as its chunk is evaluated; ``--tensorboard DIR`` adds a ``metrics_writer.TensorBoardWriter``.
    The progress line's steps/s and ETA are measured from the end of this session's first chunk, so
    they exclude compilation (the first line shows "?")."""
    run_dir = Path(s.run.out_dir)
    check_out_dir(run_dir)
    if s.run.resume:
        check_resumable(run_dir)
        s = _config_for_resume(s, run_dir)
    claim_run_dir(run_dir, s.run.resume, s.run.overwrite)  # refuse another run's directory before compiling
    state = None
    if s.run.resume:  # read (and verify) the checkpoint before anything else: is it this config's?
        state, saved_meta = ckpt.load_checkpoint(run_dir)
        ckpt.check_problem(s, saved_meta.get(ckpt.PROBLEM), run_dir / ckpt.CHECKPOINT)
    cfg, env_params = build(s)  # validates: fail before creating the run directory
    if state is not None:
        ckpt.check_device_count(state, len(jax.devices()), run_dir / ckpt.CHECKPOINT)
    writer = distributed.is_writer()  # process 0 prints and writes; the others only compute
    say = (lambda *a: None) if s.run.quiet or not writer else (lambda *a: print(*a, flush=True))
    owned = [TensorBoardWriter(s.run.tensorboard)] if s.run.tensorboard and writer else []  # needs tensorboardX
    try:
        with own_run_dir(run_dir, s.run.resume, s.run.overwrite, writer, say), finish_together("jaxtraffic.train"), \
                StopSignals(say) as stop:  # an interruption is agreed (agree_stop)
            return _train(s, cfg, env_params, run_dir, state, saved_meta if state is not None else None, say, stop,
                          [*callbacks, *owned])
    finally:
        for tb in owned:
            tb.close()


def _train(s: TrainConfig, cfg: ppo.PPOConfig, env_params: learn_env.EnvParams, run_dir: Path, state: dict | None,
           saved_meta: dict | None, say, stop: StopSignals, callbacks: list) -> Path:
    eval_steps = max(1, round(s.run.eval_horizon_s / s.plant.dt))
    say("compiling (Ctrl-C or SIGTERM from now on stops at the next safe point) ...")
    init, train_chunk = ppo.make_train(cfg, env_params, env=learn_env.GainEnv)
    evaluate = make_evaluator(cfg, env_params, eval_steps)

    t_start = time.perf_counter()
    validate = None
    if s.run.val_horizon_s > 0:
        val_steps = 2 * max(1, round(s.run.val_horizon_s / s.plant.dt / 2))
        judge = TrafficParams.reference() if s.run.val_plant == "reference" else None
        validate = validation.make_validator(env_params.traffic, val_steps, validation.validation_delays(env_params),
                                             plant=judge)
    writer = distributed.is_writer()
    runner = init(jax.random.PRNGKey(s.run.seed))
    rep = members.replicated(runner)  # the shared leaves on this process: once per chunk (a collective)
    meta = {"env_steps": 0, "wall_s": 0.0, "rows": [], "seconds_to_stop_rule": None, "stopped": False,
            ckpt.PROBLEM: ckpt.problem_of(s)}

    def policy():  # the current (params, obs mean, obs var), leading member axis
        host = jax.device_get(rep)
        return host.params, np.asarray(host.stats.mean), np.asarray(host.stats.var)

    best = validation.new_best(*policy())
    if state is not None:
        meta = {ckpt.PROBLEM: ckpt.problem_of(s), **saved_meta}  # (a checkpoint from before the binding has none)
        # every leaf placed like the fresh runner's (sharded over the mesh): uncommitted arrays would recompile
        restored = ckpt.restore_runner(runner, state, run_dir / ckpt.CHECKPOINT)
        runner = distributed.put_like(runner, restored)
        rep = members.replicated(runner)
        saved_best = ckpt.load_best(run_dir)
        if saved_best is not None:
            best = ckpt.restore_best(best, saved_best)
        if s.run.keep_going:
            meta["stopped"] = False
        say(f"resumed {run_dir} at {meta['env_steps']} env steps ({meta['wall_s']:.1f} s)")
    if writer:  # (on resume: the run-control values this session was given, recorded)
        write_json(run_dir / ckpt.CONFIG, config_dict(s, cfg, env_params))
    curve_csv = run_dir / "learning_curve.csv"
    if writer:
        write_curve(curve_csv, meta["rows"])  # header (+ the checkpoint's rows on resume) once; rows appended below
    wall0 = float(meta["wall_s"])
    rate_from: tuple[float, int] | None = None  # (time, env steps) after this session's first chunk
    steps_per_chunk = cfg.steps_per_update * cfg.updates_per_chunk
    say(f"training PPO: {cfg.num_envs} envs x {cfg.num_steps} steps/update, {cfg.updates_per_chunk} updates/chunk,"
        f" {s.run.seeds} seed(s), {len(jax.devices())} device(s), plant D = {s.plant.delay:g} s, "
        f"target eval reward >= {s.run.target_reward}")
    interrupted = False
    last_eval: dict = {}
    steps_at_start = saved_steps = meta["env_steps"]
    best_saved, consistent = best, None
    signum = agree_stop(False, False, stop)[2]
    try:
        while meta["env_steps"] < s.run.total_steps and not meta["stopped"] and signum is None:
            runner, m = train_chunk(runner)
            rep = members.replicated(runner)
            jax.block_until_ready(m)
            check_finite("the losses, statistics or parameters", {"losses": {k: m[k] for k in LOSSES},
                                                                  "params": rep.params, "stats": rep.stats}, run_dir,
                         f"{saved_steps} env steps")
            last_eval = evaluate(runner)
            meta["env_steps"] += steps_per_chunk
            ev = last_eval["final_reward"]
            paper = (ev >= s.run.target_reward) & ~np.asarray(last_eval["diverged"])
            candidate = paper & (True if s.run.min_wave_speed is None
                                 else last_eval["wave_speed"] >= s.run.min_wave_speed)
            if s.run.require_certificate:
                candidate = candidate & _certified(last_eval["equilibrium_gains"], candidate, s)
            score = validation.scores(ev, candidate, validate, functools.partial(
                member_controller, cfg, env_params, rep.params, rep.stats.mean, rep.stats.var))
            best = validation.update_best(best, score, meta["env_steps"], policy)
            meta["wall_s"] = wall0 + time.perf_counter() - t_start
            row = {"update": int(np.asarray(rep.update).max()), "env_steps": meta["env_steps"],
                   "wall_s": round(meta["wall_s"], 3), "mean_reward": float(m["mean_reward"][:, -1].mean()),
                   "eval_reward": float(ev.mean()), "eval_reward_min": float(ev.min()),
                   "eval_reward_max": float(ev.max()),
                   "eval_J_comfort": float(last_eval["J_comfort"].mean()),
                   "eval_rho_L2_veh_km": float(last_eval["final_rho_L2"].mean()) * VEH_PER_KM,
                   "eval_wave_speed": float(last_eval["wave_speed"].mean()),
                   "val_score": float(np.min(score)), "best_val_score": float(np.min(best["score"]))}
            row.update({k: float(m[k][:, -1].mean()) for k in ("eta1", "eta2", "eta3", "entropy", "approx_kl",
                                                               "value_loss")})
            meta["rows"].append(row)
            if bool(paper.any()) and meta.get("seconds_to_paper_rule") is None:
                meta["seconds_to_paper_rule"] = meta["wall_s"]
                meta["env_steps_to_paper_rule"] = meta["env_steps"]
            ok = candidate & ((score <= s.run.val_target) if validate is not None else True)
            reached = bool(ok.any())
            if reached and meta["seconds_to_stop_rule"] is None:
                meta["seconds_to_stop_rule"] = meta["wall_s"]
                meta["env_steps_to_stop_rule"] = meta["env_steps"]
            # per member: consecutive evaluations meeting the rule; a population stops on its first member
            streak = np.where(ok, np.asarray(meta.get("member_streak", [0] * cfg.num_seeds)) + 1, 0)
            meta["member_streak"] = streak.tolist()
            meta["streak"] = int(streak.max())
            if meta["streak"] >= s.run.stop_patience and not s.run.keep_going:
                meta["stopped"] = True
                meta["stop_member"] = int(np.argmax(streak))
            runner = _maybe_restart(s, meta, ok, runner, init, say)
            row["restarts"] = len(meta.get("restarts", []))
            now = time.perf_counter()
            if rate_from is None:  # the first chunk compiles: no rate yet
                rate, rate_from = math.nan, (now, meta["env_steps"])
            else:
                rate = (meta["env_steps"] - rate_from[1]) / max(1e-9, now - rate_from[0])
            eta = max(0, s.run.total_steps - meta["env_steps"]) / rate if rate > 0 else math.nan
            rate_txt = f"{rate:8.0f}" if math.isfinite(rate) else "       ?"
            say(f"[{meta['env_steps']:>9d} steps] {rate_txt} steps/s | reward {row['mean_reward']:9.3f} | "
                f"eval {row['eval_reward']:9.4f} (min {row['eval_reward_min']:.4f}) | gains "
                f"({row['eta1']:+.2f}, {row['eta2']:+.2f}, {row['eta3']:+.2f}) | s {row['eval_wave_speed']:+.2f} m/s | "
                f"val {validation.format_scores(score)} | {fmt_time(meta['wall_s'])} | "
                f"ETA {fmt_time(eta)}" + (" | stop rule reached" if reached else ""))
            # the state after this chunk, complete: saved now (a session's first chunk, every
            # checkpoint_every-th) or, if the loop ends before the next save, on the way out
            consistent = (runner, copy.deepcopy(meta))
            chunks = (meta["env_steps"] - steps_at_start) // steps_per_chunk  # this session's, >= 1
            if chunks == 1 or chunks % s.run.checkpoint_every == 0:
                _save(run_dir, runner, meta, best, writer)
                saved_steps = meta["env_steps"]
            elif writer and best_saved is not best:
                ckpt.save_best(run_dir, best, meta.get(ckpt.PROBLEM))
            best_saved = best
            if writer:
                append_curve(curve_csv, row)
                for callback in callbacks:
                    callback(row)
            meta["stopped"], over_budget, signum = agree_stop(meta["stopped"], meta["wall_s"] > s.run.max_wall_s, stop)
            if over_budget:
                say(f"stopping: wall-clock budget {s.run.max_wall_s:g} s reached")
                break
    except KeyboardInterrupt:  # raised by Python code (the handlers above turn signals into a flag)
        interrupted = True
    signum = signal.SIGINT if interrupted else signum
    interrupted = signum is not None
    if interrupted and consistent is not None and consistent[1]["env_steps"] != saved_steps:
        _save(run_dir, *consistent, best, writer)  # the last completed chunk, before saying it is saved
    if interrupted:
        msg = report_interruption(signum, run_dir, bool(meta["rows"]), meta["env_steps"] != steps_at_start,
                                  f"{meta['env_steps']} env steps")
    if not meta["rows"]:
        return run_dir
    if not interrupted:
        _save(run_dir, runner, meta, best, writer)
    if writer:
        _plot_curve(run_dir)
    if not last_eval:
        last_eval = evaluate(runner)
    ev = last_eval["final_reward"]
    best_member = int(np.argmin(best["score"]))
    summary = {
        "provenance": provenance(),
        "env_steps": meta["env_steps"], "wall_s": meta["wall_s"],
        "seconds_to_stop_rule": meta["seconds_to_stop_rule"],
        "env_steps_to_stop_rule": meta.get("env_steps_to_stop_rule"),
        "seconds_to_paper_rule": meta.get("seconds_to_paper_rule"),
        "env_steps_to_paper_rule": meta.get("env_steps_to_paper_rule"),
        "min_wave_speed": s.run.min_wave_speed,
        "stop_rule_reached": meta["seconds_to_stop_rule"] is not None, "stopped": bool(meta["stopped"]),
        "target_reward": s.run.target_reward, "interrupted": interrupted,
        "best_seed": best_member,
        "best_val_score": best["score"], "best_env_steps": best["env_steps"],
        "restarts": meta.get("restarts", []),
        "validation": None if validate is None else {"delays": validation.validation_delays(env_params),
                                                     "plant": s.run.val_plant,
                                                     "horizon_s": s.run.val_horizon_s, "target": s.run.val_target,
                                                     "reference": validate.reference},
        "final_eval": {k: v for k, v in last_eval.items()},
        "eval_horizon_s": s.run.eval_horizon_s,
    }
    if writer:
        write_json(run_dir / ckpt.SUMMARY, summary)  # load_policy reads best_seed from it
        summary["certificate"] = ckpt.policy_certificate(ckpt.load_policy(run_dir)[0], s)
        write_json(run_dir / ckpt.SUMMARY, summary)
    rule = (f"first reached after {meta['seconds_to_stop_rule']:.1f} s" if summary["stop_rule_reached"]
            else "not reached")
    say(f"done: {meta['env_steps']} env steps in {meta['wall_s']:.1f} s; eval reward per seed {np.round(ev, 4)};"
        f" stop rule {rule}; best checkpoint: member {best_member}, score {best['score'][best_member]:.3g} at "
        f"{best['env_steps'][best_member]} env steps; outputs in {run_dir}")
    if interrupted:
        raise TrainingInterrupted(signum, msg)
    return run_dir
