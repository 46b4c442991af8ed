"""Train the paper's PPO gain policy: ``python train.py [flags]`` (``--help`` lists them).

A default run trains the D = 4 s policy and writes, in ``--out-dir`` (default runs/default):
config.json, checkpoint.msgpack, learning_curve.csv/.png and summary.json. Ctrl-C saves a
checkpoint; ``--resume`` continues from it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

from jaxtraffic.learn.trainer import TrainSettings, train


def _pair(kind):
    def parse(text: str):
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected LO,HI, got {text!r}")
        return tuple(kind(p) for p in parts)
    return parse


def build_parser() -> argparse.ArgumentParser:
    d = TrainSettings()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    g = p.add_argument_group("run")
    g.add_argument("--out-dir", default=d.out_dir, help="run directory")
    g.add_argument("--resume", action="store_true",
                   help="continue from the run directory's checkpoint (its saved settings are used; only the "
                   "run-control flags --total-steps/--max-wall-s/--keep-going/--stop-patience/--target-reward/"
                   "--min-wave-speed apply)")
    g.add_argument("--seed", type=int, default=d.seed, help="PRNG seed")
    g.add_argument("--seeds", type=int, default=d.seeds, help="independent seeds trained at once (vmap)")
    g.add_argument("--total-steps", type=int, default=d.total_steps, help="environment steps (all envs, per seed)")
    g.add_argument("--max-wall-s", type=float, default=d.max_wall_s, help="stop after this many seconds")
    g.add_argument("--keep-going", action="store_true", help="ignore the stop rule")
    g.add_argument("--target-reward", type=float, default=d.target_reward,
                   help="stop rule: deterministic evaluation reward (end of the evaluation rollout) >= this")
    g.add_argument("--min-wave-speed", type=float, default=d.min_wave_speed,
                   help="stop rule also requires the closed loop's kinematic wave speed at the policy's "
                   "equilibrium gains (linear.gain_law_wave_speed, m/s) >= this; -inf: the paper's rule alone")
    g.add_argument("--stop-patience", type=int, default=d.stop_patience,
                   help="consecutive evaluations that must meet the stop rule before stopping")
    g.add_argument("--eval-horizon-s", type=float, default=d.eval_horizon_s, help="evaluation rollout length, s")
    g.add_argument("--quiet", action="store_true", help="no progress lines")
    g = p.add_argument_group("plant and grid")
    g.add_argument("--delay", type=float, default=d.delay, help="plant input delay D, s (multiple of dt)")
    g.add_argument("--alpha", type=float, default=d.alpha, help="ACC penetration rate")
    g.add_argument("--alpha-noise", type=float, default=d.alpha_noise, help="per-step std of plant alpha noise")
    g.add_argument("--n-points", type=int, default=d.n_points, help="grid points (dx = L/(n-1))")
    g.add_argument("--dt", type=float, default=d.dt, help="time step, s")
    g.add_argument("--max-delay-steps", type=int, default=d.max_delay_steps, help="delay buffer capacity, steps")
    g = p.add_argument_group("episodes and domain randomisation")
    g.add_argument("--horizon-s", type=float, default=d.horizon_s, help="episode length, s (truncation)")
    g.add_argument("--delay-spread", type=float, default=d.delay_spread,
                   help="train on plant delays ~ U(D - spread, D + spread) s (clipped at 0); 0 disables")
    g.add_argument("--delay-range", type=_pair(float), default=d.delay_range,
                   help="plant delay range LO,HI s (overrides --delay-spread)")
    g.add_argument("--alpha-range", type=_pair(float), default=d.alpha_range, help="plant alpha range LO,HI")
    g.add_argument("--amp-range", type=_pair(float), default=d.amp_range, help="initial amplitude LO,HI veh/m")
    g.add_argument("--wavenumber-range", type=_pair(int), default=d.wavenumber_range,
                   help="initial wavenumber LO,HI (integers)")
    g.add_argument("--phase-max", type=float, default=d.phase_max, help="initial phase ~ U(0, phase_max) rad")
    g.add_argument("--gain-max", type=float, default=d.gain_max, help="|eta_i| bound (normalised gains)")
    g.add_argument("--gain-filter", type=float, default=d.gain_filter,
                   help="applied gains move this fraction of the way to the policy's gains each step "
                   "(first-order filter, time constant ~ dt/k); 1: applied directly (the paper)")
    g.add_argument("--h-rate-weight", type=float, default=d.h_rate_weight,
                   help="training reward -= w * sum_i ((h_i - h_prev_i)/h_bar)^2, the squared step change of "
                   "the commanded time gap (dimensionless); 0: the paper's reward")
    g = p.add_argument_group("PPO")
    g.add_argument("--num-envs", type=int, default=d.num_envs, help="parallel environments per seed")
    g.add_argument("--num-steps", type=int, default=d.num_steps, help="rollout steps per update (100 = 10 s)")
    g.add_argument("--update-epochs", type=int, default=d.update_epochs, help="epochs per update")
    g.add_argument("--num-minibatches", type=int, default=d.num_minibatches, help="minibatches per epoch")
    g.add_argument("--updates-per-chunk", type=int, default=d.updates_per_chunk,
                   help="updates per jit-compiled chunk (progress/checkpoint interval)")
    g.add_argument("--network", choices=("small", "paper"), default=d.network,
                   help="small: 2x64 tanh MLPs; paper: 8 layers (1024, then 512 units)")
    g.add_argument("--lr", type=float, default=d.lr, help="Adam learning rate")
    g.add_argument("--lr-decay-steps", type=float, default=d.lr_decay_steps,
                   help="env steps (per seed) over which the learning rate falls linearly to lr * lr-final; "
                   "0: constant")
    g.add_argument("--lr-final", type=float, default=d.lr_final, help="final learning rate, as a fraction of --lr")
    g.add_argument("--gamma", type=float, default=d.gamma, help="discount")
    g.add_argument("--gae-lambda", type=float, default=d.gae_lambda, help="GAE lambda")
    g.add_argument("--clip-eps", type=float, default=d.clip_eps, help="PPO clip range")
    g.add_argument("--ent-coef", type=float, default=d.ent_coef, help="entropy bonus")
    g.add_argument("--vf-coef", type=float, default=d.vf_coef, help="value loss weight")
    g.add_argument("--max-grad-norm", type=float, default=d.max_grad_norm, help="gradient clipping")
    g.add_argument("--reward-scale", type=float, default=d.reward_scale, help="reward multiplier for learning")
    g.add_argument("--init-sigma", type=float, default=d.init_sigma, help="initial action std (pre-tanh)")
    return p


def settings_from_args(argv: list[str] | None = None) -> TrainSettings:
    args = build_parser().parse_args(argv)
    if args.min_wave_speed == -math.inf:  # the paper's rule alone (stored as null in the JSON outputs)
        args.min_wave_speed = None
    names = {f.name for f in dataclasses.fields(TrainSettings)}
    return TrainSettings(**{k: v for k, v in vars(args).items() if k in names})


def main(argv: list[str] | None = None) -> Path:
    """Parse flags, train, return the run directory."""
    try:
        settings = settings_from_args(argv)
        return train(settings)
    except ValueError as err:  # invalid parameters: a clear message, no traceback
        print(f"train.py: error: {err}", file=sys.stderr)
        raise SystemExit(2) from err

