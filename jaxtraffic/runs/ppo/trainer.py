"""PPO's part of a training run (``runs.loop.run_training`` does the rest): chunks, evaluation, stop rule,
random restarts, best checkpoints.

``train(config)`` runs jit-compiled chunks of PPO updates (``algorithm.make_train``). After each chunk it
evaluates the deterministic policy of every member (seed) on the paper's initial condition (``eval_horizon_s``,
the training plant without randomisation) and applies the stop rule unless ``keep_going``. A member meets the
rule at an evaluation when (1) the paper's rule holds (evaluation reward, i.e. the reward at the end of the
evaluation rollout, >= ``target_reward``, no divergence); (2) with ``min_wave_speed`` set, the closed loop
under the gains its policy settles to at the equilibrium carries density waves downstream at least that fast
(``linear.gain_law_wave_speed``, m/s: a backward wave speed leaves a slow mode that enters at the outlet and
never decays, which the 300 s evaluation reward hardly sees), and with ``require_certificate`` those gains
are certified (``control.stability``: the delayed, filtered law's linearised closed loop grows at no
wavenumber faster than 1e-3/s at the training delay and alpha); (3) with a validation suite (``val_horizon_s``
> 0, ``selection``), its validation score is <= ``val_target``. The suite is rolled out only for evaluations
that pass (1) and (2). A run trained on the train split (``EnvConfig.train_split``) is validated on it
(``selection.make_split_suite``; with ``val_horizon_s`` > 0) and drops (1) from the conditions; a checkpoint that
fails (2) still ranks, below every one that passes, by its evaluation reward on the paper's wave, or in a split run
by its suite score on the train split (``selection.scores``): a split run none of whose evaluations passes (2)
keeps the one best on its train split, never the one best on the paper's wave.
The run stops when one member has met the rule
at ``stop_patience`` consecutive evaluations (default 1). ``seconds_to_stop_rule`` records the first time it held,
``seconds_to_paper_rule`` the first time (1) alone held.

Each member's best checkpoint (lowest validation score; checkpoints that fail (1)-(2) rank below every
validated one, by evaluation reward) is kept in ``best.msgpack``; the member with the best score is
``summary.json``'s ``best_seed`` and the policy ``load_policy`` returns. ``resume`` continues exactly from the
checkpoint, best checkpoints included.

The learning curve's evaluation columns are means over members of the deterministic rollout: eval_reward (the
paper's reward at its end, dimensionless; eval_reward_min and eval_reward_max: the worst and best member's),
eval_J_comfort, eval_rho_L2_veh_km (final density L2 deviation in veh/km) and eval_wave_speed (m/s, see
above); val_score and best_val_score are the lowest over members (``selection.Validation`` tells a score's
status).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.gain_policy import equilibrium_gains, policy_controller
from jaxtraffic.control.stability import certify
from jaxtraffic.io.files import write_json
from jaxtraffic.learn import env as learn_env
from jaxtraffic.learn.ppo import algorithm
from jaxtraffic.model.linear import gain_law_wave_speed, linearize
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.platform import distributed
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, config_json
from jaxtraffic.runs.config.checks import check_devices, check_initial_amplitudes, check_memory
from jaxtraffic.runs.curve import CURVE_FIELDS
from jaxtraffic.runs.loop import Clock, Progress, prepare, run_training, summary_base
from jaxtraffic.runs.policy import load_policy, policy_certificate
from jaxtraffic.runs.ppo import members, selection
from jaxtraffic.runs.session import check_finite, check_total, eta_text, fmt_time, rounding_note
from jaxtraffic.sim.initial import paper_initial_condition
from jaxtraffic.sim.rollout import simulate_batch

__all__ = ["build", "make_evaluator", "member_controller", "train"]

LOSSES = ("mean_reward", "value_loss", "entropy", "approx_kl")  # a chunk's metrics that must stay finite
MILESTONES = ("stop_rule", "paper_rule")


def build(config: TrainConfig) -> tuple[algorithm.PPOConfig, learn_env.EnvParams]:
    """PPO's settings and the environment's parameters of a ``TrainConfig``, checked against this machine
    (devices, memory) and the plant (initial amplitudes)."""
    ppo_config = config.ppo
    algorithm.check_ppo_config(ppo_config)
    env_params = config.env_params()
    check_devices(config, len(jax.devices()))
    check_memory(config)
    check_initial_amplitudes(config, env_params.traffic)
    return ppo_config, env_params


def member_controller(ppo_config: algorithm.PPOConfig, env_params: learn_env.EnvParams, params, obs_mean, obs_var):
    """Deterministic policy controller whose parameters carry a leading member (seed) axis."""
    n = obs_mean.shape[0]
    gain_max = jnp.asarray(env_params.gain_max, float)
    return policy_controller(params, obs_mean, obs_var, jnp.broadcast_to(gain_max, (n,) + gain_max.shape),
                             hidden=tuple(ppo_config.hidden), init_sigma=ppo_config.init_sigma,
                             gain_filter=env_params.gain_filter, obs_segments=env_params.obs_segments,
                             sigma_nodes=env_params.filter_nodes)


def make_evaluator(ppo_config: algorithm.PPOConfig, env_params: learn_env.EnvParams, eval_steps: int):
    """Deterministic evaluation of every member's policy on the paper's initial condition.

    Returns ``evaluate(runner) -> dict`` of per-member metrics (final_reward, J's, ...), plus the gains each
    policy settles to at the equilibrium (``equilibrium_gains``, (M, 3)) and the closed loop's kinematic wave
    speed under them (``wave_speed``, m/s, ``linear.gain_law_wave_speed``)."""
    plant = env_params.traffic.replace(alpha_noise=0.0)
    rho0, v0 = paper_initial_condition(plant)
    lm = linearize(plant)

    @jax.jit
    @jax.vmap
    def equilibrium_diagnostics(ctrl):  # one member's controller
        gains = equilibrium_gains(ctrl, plant)
        return gains, gain_law_wave_speed(gains, lm)

    def evaluate(runner: algorithm.Runner) -> dict:
        rep = members.replicated(runner)  # settings with a leading member axis: one batched rollout
        ctrl = member_controller(ppo_config, env_params, rep.params, rep.stats.mean, rep.stats.var)
        res = simulate_batch(plant, ctrl, n_steps=eval_steps, rho0=rho0, v0=v0, batch_controller=True)
        out = {k: np.asarray(v) for k, v in res.metrics.items()}
        gains, speed = equilibrium_diagnostics(ctrl)
        out.update(equilibrium_gains=np.asarray(gains), wave_speed=np.asarray(speed))
        return out

    return evaluate


def _certified(gains: np.ndarray, candidate: np.ndarray, config: TrainConfig) -> np.ndarray:
    """Per member: whether its equilibrium ``gains`` ((M, 3)) are certified (``control.stability``) at the
    training delay and alpha with the law's filter; computed for the ``candidate`` members only."""
    nominal = config.plant.replace(alpha_noise=0.0)
    return np.array([bool(c) and certify(g, nominal, float(config.plant.delay), config.env.filter_sigma).stable
                     for g, c in zip(np.asarray(gains), np.asarray(candidate), strict=True)])


@dataclass
class Members:
    """PPO's per-member bookkeeping, saved in the checkpoint's progress (``Progress.own``), so that a resumed
    run stops and restarts exactly where an uninterrupted one would: per member, the consecutive evaluations
    meeting the stop rule (``streak``), the env steps at its (re)start and whether it has met the rule since
    (``start_steps``, ``met``); the restarts (one ``{"env_steps", "members"}`` entry each) and the member that
    stopped the run."""

    streak: list[int]
    start_steps: list[int]
    met: list[bool]
    restarts: list[dict] = field(default_factory=list)
    stop_member: int | None = None

    @classmethod
    def of(cls, own: dict, n: int) -> Members:
        """The record saved in ``own`` (a checkpoint's progress), or a fresh one for ``n`` members."""
        return cls(streak=list(own.get("member_streak", [0] * n)),
                   start_steps=list(own.get("member_start_steps", [0] * n)),
                   met=list(own.get("member_met", [False] * n)), restarts=list(own.get("restarts", [])),
                   stop_member=own.get("stop_member"))

    def to_own(self) -> dict:
        """The record as saved."""
        return {"member_streak": self.streak, "member_start_steps": self.start_steps,
                "member_met": self.met, "restarts": self.restarts,
                **({} if self.stop_member is None else {"stop_member": self.stop_member})}


class PPOTraining:
    """PPO's hooks for ``runs.loop`` (``runs.loop.Algorithm``)."""

    unit = "env steps"
    curve_fields = CURVE_FIELDS
    curve_title: str | None = None

    def __init__(self, config: TrainConfig, ppo_config: algorithm.PPOConfig, env_params: learn_env.EnvParams,
                 run_dir: Path) -> None:
        self.config, self.ppo_config, self.env_params, self.run_dir = config, ppo_config, env_params, run_dir
        run = config.run
        self.total, self.checkpoint_every = run.total_steps, run.checkpoint_every
        self.init, self.train_chunk = algorithm.make_train(ppo_config, env_params, env=learn_env.TrafficEnv)
        self.evaluate = make_evaluator(ppo_config, env_params, max(1, round(run.eval_horizon_s / config.plant.dt)))
        self.suite = None
        # trained on the train split and validated: selected on that split, not on the paper's wave
        self.split = config.env.train_split > 0 and run.val_horizon_s > 0
        if run.val_horizon_s > 0:
            judge = TrafficParams.reference() if run.val_plant == "reference" else None
            if self.split:
                self.suite = selection.make_split_suite(env_params.traffic, run.val_horizon_s,
                                                        config.env.train_split, plant=judge,
                                                        sensor_noise=config.env.train_sensor_noise)
            else:
                val_steps = 2 * max(1, round(run.val_horizon_s / config.plant.dt / 2))
                self.suite = selection.make_suite(env_params.traffic, val_steps,
                                                  selection.validation_delays(env_params), plant=judge)
        self.steps_per_chunk = ppo_config.steps_per_update * ppo_config.updates_per_chunk
        self.last_eval: dict = {}
        self.last_checks: tuple[np.ndarray | None, np.ndarray | None] = (None, None)

    def _policy(self):  # the current (params, obs mean, obs var), leading member axis
        host = jax.device_get(self.rep)
        return host.params, np.asarray(host.stats.mean), np.asarray(host.stats.var)

    def start(self, saved: tuple[Any, dict] | None, say: Callable[..., None]) -> str:
        self.say = say
        self.runner = self.init(jax.random.PRNGKey(self.config.run.seed))
        self.rep = members.replicated(self.runner)  # the shared leaves on this process (a collective)
        self.best = selection.BestCheckpoints.empty(*self._policy())
        self.progress = Progress("env_steps", MILESTONES)
        if saved is not None:
            state, meta = saved  # (its device count was checked by ``train``)
            self.progress = Progress.from_meta(meta, "env_steps", MILESTONES)
            # every leaf placed like the fresh runner's (sharded over the mesh): uncommitted arrays would recompile
            restored = ckpt.restore_runner(self.runner, state, self.run_dir / ckpt.CHECKPOINT)
            self.runner = distributed.put_like(self.runner, restored)
            self.rep = members.replicated(self.runner)
            saved_best = ckpt.load_best(self.run_dir)
            if saved_best is not None:
                self.best = self.best.restored(saved_best)
            if self.config.run.keep_going:
                self.progress.stopped = False
        self.members = Members.of(self.progress.own, self.ppo_config.num_seeds)
        self.best_saved = self.best
        c, run = self.ppo_config, self.config.run
        note = rounding_note(run.total_steps, self.steps_per_chunk, "--total-steps", "env steps", f"{c.num_envs} "
                             f"envs x {c.num_steps} steps x {c.updates_per_chunk} updates per member")
        return (f"training PPO: {c.num_envs} envs x {c.num_steps} steps/update, {c.updates_per_chunk} updates/chunk,"
                f" {c.num_seeds} seed(s), {len(jax.devices())} device(s), plant D = {self.config.plant.delay:g} s, "
                f"target eval reward >= {run.target_reward}" + (f"\n{note}" if note else ""))

    def _judge(self, ev: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(paper rule met, stop rule met, score) per member, of one evaluation."""
        run = self.config.run
        reward = ev["final_reward"]
        paper = (reward >= run.target_reward) & ~np.asarray(ev["diverged"])
        # a split run's candidates are not judged on the paper's wave: only its policy's equilibrium properties
        candidate = (np.ones_like(paper) if self.split else paper) & (
            True if run.min_wave_speed is None else ev["wave_speed"] >= run.min_wave_speed)
        certified = _certified(ev["equilibrium_gains"], candidate, self.config) if run.require_certificate else None
        candidate = candidate if certified is None else candidate & certified
        score = selection.scores(reward, candidate, self.suite, functools.partial(
            member_controller, self.ppo_config, self.env_params, self.rep.params, self.rep.stats.mean,
            self.rep.stats.var), rank_all=self.split)
        ok = candidate & ((score <= run.val_target) if self.suite is not None else True)
        self.last_checks = (certified, score)  # for the closing line (selection.rule_text)
        return paper, ok, score

    def chunk(self, clock: Clock) -> tuple[dict, str]:
        prog, run = self.progress, self.config.run
        saved_at = prog.env_steps
        self.runner, m = self.train_chunk(self.runner)
        self.rep = members.replicated(self.runner)
        jax.block_until_ready(m)
        check_finite("the losses, statistics or parameters", {"losses": {k: m[k] for k in LOSSES},
                                                              "params": self.rep.params, "stats": self.rep.stats},
                     self.run_dir, f"{saved_at} env steps")
        ev = self.last_eval = self.evaluate(self.runner)
        prog.env_steps += self.steps_per_chunk
        paper, ok, score = self._judge(ev)
        self.best = self.best.update(score, prog.env_steps, self._policy)
        prog.wall_s = clock.wall()
        row = self._row(m, ev, score)
        prog.rows.append(row)
        prog.mark("paper_rule", bool(paper.any()))
        prog.mark("stop_rule", bool(ok.any()))
        # per member: consecutive evaluations meeting the rule; a population stops on its first member
        streak = np.where(ok, np.asarray(self.members.streak) + 1, 0)
        self.members.streak = streak.tolist()
        if int(streak.max()) >= run.stop_patience and not run.keep_going:
            prog.stopped = True
            self.members.stop_member = int(np.argmax(streak))
        self.runner = self._maybe_restart(ok)
        row["restarts"] = len(self.members.restarts)
        prog.own = self.members.to_own()
        rate = clock.rate(prog.env_steps)
        rate_txt = f"{rate:8.0f}" if math.isfinite(rate) else "       ?"
        line = (f"[{prog.env_steps:>9d} steps] {rate_txt} steps/s | reward {row['mean_reward']:9.3f} | "
                f"eval {row['eval_reward']:9.4f} (min {row['eval_reward_min']:.4f}) | gains "
                f"({row['eta1']:+.2f}, {row['eta2']:+.2f}, {row['eta3']:+.2f}) | s {row['eval_wave_speed']:+.2f} m/s | "
                f"val {selection.format_scores(score)} | {fmt_time(prog.wall_s)} | "
                f"{eta_text(run.total_steps - prog.env_steps, rate)}" + (" | stop rule reached" if ok.any() else ""))
        return row, line

    def _row(self, m: dict, ev: dict, score: np.ndarray) -> dict:
        """The chunk's learning-curve row (``curve.CURVE_FIELDS``)."""
        prog, reward = self.progress, ev["final_reward"]
        row = {"update": int(np.asarray(self.rep.update).max()), "env_steps": prog.env_steps,
               "wall_s": round(prog.wall_s, 3), "mean_reward": float(m["mean_reward"][:, -1].mean()),
               "eval_reward": float(reward.mean()), "eval_reward_min": float(reward.min()),
               "eval_reward_max": float(reward.max()), "eval_J_comfort": float(ev["J_comfort"].mean()),
               "eval_rho_L2_veh_km": float(ev["final_rho_L2"].mean()),
               "eval_wave_speed": float(ev["wave_speed"].mean()),
               "val_score": float(np.min(score)), "best_val_score": float(np.min(self.best.score))}
        row.update({k: float(m[k][:, -1].mean()) for k in ("eta1", "eta2", "eta3", "entropy", "approx_kl",
                                                           "value_loss")})
        return row

    def _maybe_restart(self, ok: np.ndarray):
        """Random restarts: re-initialise every member that has not met the stop rule (``ok``) within
        ``run.restart_steps`` env steps of its (re)start, from the key ``fold_in(seed key, restart number)``; the
        best checkpoints are kept. Bookkeeping in ``self.members`` (``Members``: saved with the checkpoint)."""
        prog, run, own = self.progress, self.config.run, self.members
        start = np.asarray(own.start_steps)
        met = np.asarray(own.met) | ok
        due = (~met) & (prog.env_steps - start >= run.restart_steps)
        stopped = prog.stopped
        if run.restart_steps and not run.keep_going:  # process 0's decision on every process (a collective)
            votes = distributed.agree([*due.astype(int), int(stopped)])[0]
            due, stopped = votes[:-1].astype(bool), bool(votes[-1])
        if (not run.restart_steps or run.keep_going or stopped or prog.env_steps >= run.total_steps
                or not due.any()):
            own.start_steps, own.met = start.tolist(), met.tolist()
            return self.runner
        restarts = own.restarts
        restarts.append({"env_steps": prog.env_steps, "members": np.flatnonzero(due).tolist()})
        fresh = self.init(jax.random.fold_in(jax.random.PRNGKey(run.seed), len(restarts)))
        own.start_steps = np.where(due, prog.env_steps, start).tolist()
        own.met = np.where(due, False, met).tolist()
        self.say(f"restart {len(restarts)}: member(s) {restarts[-1]['members']} re-initialised (stop rule not met "
                 f"within {run.restart_steps} env steps of their start; best checkpoints kept)")
        return members.restart_members(self.runner, fresh, due)

    def snapshot(self):
        return self.runner

    def save(self, runner, meta: dict, run_dir: Path, writer: bool) -> None:
        host = distributed.to_host(runner)  # gathered on every process: a collective
        if writer:
            ckpt.save_checkpoint(run_dir, host, meta)
            ckpt.save_best(run_dir, self.best.state_dict(), meta.get(ckpt.PROBLEM))
        self.best_saved = self.best

    def saved_best(self, run_dir: Path, writer: bool) -> None:
        if writer and self.best_saved is not self.best:
            ckpt.save_best(run_dir, self.best.state_dict(), ckpt.problem_of(self.config))
        self.best_saved = self.best

    def finish(self, interrupted: bool, run_dir: Path, writer: bool) -> str:
        prog, run, best = self.progress, self.config.run, self.best
        ev = self.last_eval or self.evaluate(self.runner)
        best_member = int(np.argmin(best.score))
        summary = {
            **summary_base(prog, interrupted, run.eval_horizon_s),
            "min_wave_speed": run.min_wave_speed, "stop_rule_reached": prog.seconds_to("stop_rule") is not None,
            "stopped": bool(prog.stopped), "target_reward": run.target_reward, "best_seed": best_member,
            "best_val_score": best.score, "best_env_steps": best.env_steps,
            "restarts": self.members.restarts,
            "validation": None if self.suite is None else {
                **self.suite.scenarios, "plant": run.val_plant, "horizon_s": run.val_horizon_s,
                "target": run.val_target, "reference": self.suite.reference},
            "final_eval": dict(ev)}
        if writer:
            write_json(run_dir / ckpt.SUMMARY, summary)  # load_policy reads best_seed from it
            summary["certificate"] = policy_certificate(load_policy(run_dir)[0], self.config)
            write_json(run_dir / ckpt.SUMMARY, summary)
        sec = prog.seconds_to("stop_rule")
        rule = (f"first reached after {sec:.1f} s" if sec is not None else "not reached; at the last evaluation: "
                + selection.rule_text(run, ev, *(self.last_checks if self.last_eval else (None, None)),
                                      paper_rule=not self.split))
        best_line = selection.best_text(float(best.score[best_member]), best_member,
                                        int(best.env_steps[best_member]),
                                        None if self.suite is None else self.suite.measure, rank_all=self.split)
        return (f"done: {prog.env_steps} env steps in {prog.wall_s:.1f} s; eval reward per seed "
                f"{np.round(ev['final_reward'], 4)} (dimensionless)\nstop rule {rule}\n{best_line}\n"
                f"outputs in {run_dir}")


def config_file(config: TrainConfig, env_params: learn_env.EnvParams) -> dict:
    """The run's config.json content: the config tree, plus the facts of the run the tree does not hold (the
    episode length in steps, the devices, the jax version)."""
    return config_json(config, horizon_steps=int(env_params.horizon), devices=[str(d) for d in jax.devices()],
                       jax_version=jax.__version__)


def train(config: TrainConfig, callbacks: Sequence[Callable[[dict], None]] = ()) -> Path:
    """Train (or resume) PPO and return the run directory; raises ``TrainingInterrupted`` after SIGINT or
    SIGTERM (the checkpoint of the last completed chunk is on disk). ``callbacks``: each learning-curve row
    (a dict with the ``CURVE_FIELDS``) as soon as its chunk is evaluated."""
    config, run_dir, saved = prepare(config)
    ppo_config, env_params = build(config)  # validates: fail before creating the run directory
    if saved is not None:
        ckpt.check_device_count(saved[0], len(jax.devices()), run_dir / ckpt.CHECKPOINT)
        check_total(saved[1], "env_steps", config.run.total_steps, "--total-steps", run_dir / ckpt.CHECKPOINT)
    return run_training(config, run_dir, saved, lambda: PPOTraining(config, ppo_config, env_params, run_dir),
                        lambda: config_file(config, env_params), callbacks, "jaxtraffic.train")
