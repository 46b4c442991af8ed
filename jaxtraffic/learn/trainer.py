"""Training loop around ``ppo.make_train``: chunks, evaluation, stop rule, checkpoints, outputs.

``train(settings)`` runs jit-compiled chunks of PPO updates. Between chunks it evaluates the
deterministic policy of every seed on the paper's initial condition (``eval_horizon_s``, the
training plant without randomisation), prints a progress line, rewrites ``learning_curve.csv``
and the checkpoint atomically, and applies the paper's stop rule (evaluation reward, i.e. the
reward at the end of the evaluation rollout, >= ``target_reward`` for every seed) unless
``keep_going``. With ``min_wave_speed`` set, the rule also asks that the closed loop under the
gains each policy settles to at the equilibrium carries density waves downstream at least that
fast (``linear.gain_law_wave_speed``, m/s): a policy with a backward wave speed leaves a slow mode
that enters at the outlet and never decays, which the 300 s evaluation reward hardly sees. The
rule must hold at ``stop_patience`` consecutive evaluations (default 2: the deterministic
evaluation is noisy early on, and a single lucky evaluation gave fragile policies);
``seconds_to_stop_rule`` records the first time it held, ``seconds_to_paper_rule`` the first time
the paper's reward condition alone held. Ctrl-C saves the last completed chunk; ``resume``
continues from it exactly.

Run directory: config.json, checkpoint.msgpack, learning_curve.csv, learning_curve.png,
summary.json. The curve's evaluation columns are means over seeds of the deterministic rollout:
eval_reward (the paper's reward at its end, dimensionless), eval_J_comfort, eval_rho_L2 (final
density L2 deviation, veh/km) and eval_wave_speed (m/s, see above).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.gain_policy import equilibrium_gains, policy_controller
from jaxtraffic.learn import checkpoint as ckpt
from jaxtraffic.learn import env as E
from jaxtraffic.learn import ppo
from jaxtraffic.learn.config import RUN_CONTROL, TrainConfig, config_json, load_config
from jaxtraffic.learn.curve import CURVE_FIELDS, plot_learning_curve, write_curve
from jaxtraffic.model.linear import gain_law_wave_speed, linearize
from jaxtraffic.provenance import provenance
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.rollout import simulate_batch

__all__ = ["CURVE_FIELDS", "TrainConfig", "build", "config_dict", "make_evaluator", "train"]


def build(s: TrainConfig) -> tuple[ppo.PPOConfig, E.EnvParams]:
    """PPO config and environment parameters from a ``TrainConfig`` (validated)."""
    traffic = s.plant.traffic()
    pl, en = s.plant, s.env
    d_lo, d_hi = en.delay_range or (max(0.0, pl.delay - en.delay_spread), pl.delay + en.delay_spread)
    d_lo, d_hi = (round(d / pl.dt) * pl.dt for d in (d_lo, d_hi))
    a_lo, a_hi = en.alpha_range or (pl.alpha, pl.alpha)
    env_params = E.make_env_params(
        traffic, horizon=max(1, round(en.horizon_s / pl.dt)), gain_max=en.gain_max, amp_min=en.amp_range[0],
        amp_max=en.amp_range[1], wavenumber_min=int(en.wavenumber_range[0]),
        wavenumber_max=int(en.wavenumber_range[1]), phase_max=en.phase_max, delay_min=d_lo, delay_max=d_hi,
        alpha_min=a_lo, alpha_max=a_hi, gain_filter=en.gain_filter, h_rate_weight=en.h_rate_weight)
    algo = dataclasses.asdict(s.algo)
    cfg = ppo.PPOConfig(num_seeds=s.run.seeds, hidden=s.algo.hidden(),
                        **{f.name: algo[f.name] for f in dataclasses.fields(ppo.PPOConfig) if f.name in algo})
    ppo.validate_config(cfg)
    return cfg, env_params


def config_dict(s: TrainConfig, cfg: ppo.PPOConfig, env_params: E.EnvParams) -> dict:
    """The run's config.json content (``config.config_json``): the config tree, plus the facts of the
    run that the tree does not hold (the episode length in steps, the devices, the jax version)."""
    return config_json(s, horizon_steps=int(env_params.horizon), devices=[str(d) for d in jax.devices()],
                       jax_version=jax.__version__)


def make_evaluator(cfg: ppo.PPOConfig, env_params: E.EnvParams, eval_steps: int):
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
        rep = ppo.replicated(runner)  # settings with a leading seed axis: one batched rollout
        ctrl = policy_controller(rep.params, rep.stats.mean, rep.stats.var,
                                 jnp.full((cfg.num_seeds,), env_params.gain_max), hidden=tuple(cfg.hidden),
                                 init_sigma=cfg.init_sigma,
                                 gain_filter=env_params.gain_filter)
        res = simulate_batch(plant, ctrl, n_steps=eval_steps, rho0=rho0, v0=v0, batch_controller=True)
        out = {k: np.asarray(v) for k, v in res.metrics.items()}
        gains, speed = equilibrium_diagnostics(ctrl)
        out.update(equilibrium_gains=np.asarray(gains), wave_speed=np.asarray(speed))
        return out

    return evaluate


def _plot_curve(run_dir: Path) -> None:
    plot_learning_curve(run_dir / "learning_curve.csv", run_dir / "learning_curve.png")


def _fmt_time(sec: float) -> str:
    if not math.isfinite(sec):
        return "?"
    m, s = divmod(int(sec), 60)
    return f"{m}m{s:02d}s"


def _settings_for_resume(s: TrainConfig, run_dir: Path) -> TrainConfig:
    """The run's saved config, with only the run-control fields (``config.RUN_CONTROL``) taken from ``s``."""
    flat = s.flat()
    return load_config(run_dir).replace(**{k: flat[k] for k in RUN_CONTROL})


def train(s: TrainConfig) -> Path:
    """Train (or resume) and return the run directory."""
    run_dir = Path(s.run.out_dir)
    if s.run.resume and (run_dir / ckpt.CONFIG).exists():
        s = _settings_for_resume(s, run_dir)
    cfg, env_params = build(s)  # validates: fail before creating the run directory
    run_dir.mkdir(parents=True, exist_ok=True)
    eval_steps = max(1, round(s.run.eval_horizon_s / s.plant.dt))
    init, train_chunk = ppo.make_train(cfg, env_params, env=E.GainEnv)
    evaluate = make_evaluator(cfg, env_params, eval_steps)
    say = (lambda *a: None) if s.run.quiet else (lambda *a: print(*a, flush=True))

    t_start = time.perf_counter()
    runner = init(jax.random.PRNGKey(s.run.seed))
    meta = {"env_steps": 0, "wall_s": 0.0, "rows": [], "seconds_to_stop_rule": None, "stopped": False}
    if s.run.resume and (run_dir / ckpt.CHECKPOINT).exists():
        state, meta = ckpt.load_checkpoint(run_dir)
        # place every leaf like the fresh runner's (pmap-sharded): uncommitted arrays would recompile
        runner = jax.tree.map(lambda t, x: jax.device_put(x, t.sharding), runner, ckpt.restore_runner(runner, state))
        if s.run.keep_going:
            meta["stopped"] = False
        say(f"resumed {run_dir} at {meta['env_steps']} env steps ({meta['wall_s']:.1f} s)")
    else:
        ckpt.write_json(run_dir / ckpt.CONFIG, config_dict(s, cfg, env_params))
    wall0 = float(meta["wall_s"])
    steps_per_chunk = cfg.steps_per_update * cfg.updates_per_chunk
    say(f"training PPO: {cfg.num_envs} envs x {cfg.num_steps} steps/update, {cfg.updates_per_chunk} updates/chunk,"
        f" {s.run.seeds} seed(s), {len(jax.devices())} device(s), plant D = {s.plant.delay:g} s, "
        f"target eval reward >= {s.run.target_reward}")
    interrupted = False
    last_eval: dict = {}
    try:
        while meta["env_steps"] < s.run.total_steps and not meta["stopped"]:
            runner, m = train_chunk(runner)
            jax.block_until_ready(m)
            last_eval = evaluate(runner)
            meta["env_steps"] += steps_per_chunk
            meta["wall_s"] = wall0 + time.perf_counter() - t_start
            ev = last_eval["final_reward"]
            row = {"update": int(np.asarray(ppo.replicated(runner).update).max()), "env_steps": meta["env_steps"],
                   "wall_s": round(meta["wall_s"], 3), "mean_reward": float(m["mean_reward"][:, -1].mean()),
                   "eval_reward": float(ev.mean()), "eval_reward_min": float(ev.min()),
                   "eval_J_comfort": float(last_eval["J_comfort"].mean()),
                   "eval_rho_L2": float(last_eval["final_rho_L2"].mean()) * 1000.0,
                   "eval_wave_speed": float(last_eval["wave_speed"].mean())}
            row.update({k: float(m[k][:, -1].mean()) for k in ("eta1", "eta2", "eta3", "entropy", "approx_kl",
                                                               "value_loss")})
            meta["rows"].append(row)
            paper_rule = bool(np.all(ev >= s.run.target_reward)) and not bool(np.any(last_eval["diverged"]))
            if paper_rule and meta.get("seconds_to_paper_rule") is None:
                meta["seconds_to_paper_rule"] = meta["wall_s"]
                meta["env_steps_to_paper_rule"] = meta["env_steps"]
            reached = paper_rule and (s.run.min_wave_speed is None
                                      or bool(np.all(last_eval["wave_speed"] >= s.run.min_wave_speed)))
            if reached and meta["seconds_to_stop_rule"] is None:
                meta["seconds_to_stop_rule"] = meta["wall_s"]
                meta["env_steps_to_stop_rule"] = meta["env_steps"]
            meta["streak"] = meta.get("streak", 0) + 1 if reached else 0
            if meta["streak"] >= s.run.stop_patience and not s.run.keep_going:
                meta["stopped"] = True
            rate = steps_per_chunk / max(1e-9, (meta["wall_s"] - (meta["rows"][-2]["wall_s"] if len(meta["rows"]) > 1
                                                                  else wall0)))
            eta = (s.run.total_steps - meta["env_steps"]) / max(rate, 1e-9)
            say(f"[{meta['env_steps']:>9d} steps] {rate:8.0f} steps/s | reward {row['mean_reward']:9.3f} | "
                f"eval {row['eval_reward']:9.4f} (min {row['eval_reward_min']:.4f}) | gains "
                f"({row['eta1']:+.2f}, {row['eta2']:+.2f}, {row['eta3']:+.2f}) | s {row['eval_wave_speed']:+.2f} m/s | "
                f"{_fmt_time(meta['wall_s'])} | "
                f"ETA {_fmt_time(eta)}" + (" | stop rule reached" if reached else ""))
            ckpt.save_checkpoint(run_dir, runner, meta)
            write_curve(run_dir / "learning_curve.csv", meta["rows"])
            if meta["wall_s"] > s.run.max_wall_s:
                say(f"stopping: wall-clock budget {s.run.max_wall_s:g} s reached")
                break
    except KeyboardInterrupt:
        interrupted = True
        say("interrupted: last completed chunk is saved; continue with --resume")
    if not meta["rows"]:
        return run_dir
    if not interrupted:
        ckpt.save_checkpoint(run_dir, runner, meta)
    write_curve(run_dir / "learning_curve.csv", meta["rows"])
    _plot_curve(run_dir)
    if not last_eval:
        last_eval = evaluate(runner)
    ev = last_eval["final_reward"]
    summary = {
        "provenance": provenance(),
        "env_steps": meta["env_steps"], "wall_s": meta["wall_s"],
        "seconds_to_stop_rule": meta["seconds_to_stop_rule"],
        "env_steps_to_stop_rule": meta.get("env_steps_to_stop_rule"),
        "seconds_to_paper_rule": meta.get("seconds_to_paper_rule"),
        "env_steps_to_paper_rule": meta.get("env_steps_to_paper_rule"),
        "min_wave_speed": s.run.min_wave_speed,
        "stop_rule_reached": meta["seconds_to_stop_rule"] is not None,
        "target_reward": s.run.target_reward, "interrupted": interrupted,
        "best_seed": int(np.argmax(ev)),
        "final_eval": {k: v for k, v in last_eval.items()},
        "eval_horizon_s": s.run.eval_horizon_s,
    }
    ckpt.write_json(run_dir / ckpt.SUMMARY, summary)
    rule = (f"first reached after {meta['seconds_to_stop_rule']:.1f} s" if summary["stop_rule_reached"]
            else "not reached")
    say(f"done: {meta['env_steps']} env steps in {meta['wall_s']:.1f} s; eval reward per seed {np.round(ev, 4)};"
        f" stop rule {rule}; outputs in {run_dir}")
    return run_dir
