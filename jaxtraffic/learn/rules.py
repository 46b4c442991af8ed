"""The allowed range of every hyperparameter, by its one name, defined once (``RULES``).

A name is the config tree's field (``learn.config``), its flag (``--`` + the name with dashes) and the field of
the struct that uses it (``learn.env.EnvParams``, ``learn.ppo.PPOConfig``, ``learn.gradient.GradientConfig``).
The config tree (``learn.config.checks``), ``learn.env.make_env_params``, ``learn.ppo.check_ppo_config`` and
``GradientConfig.__post_init__`` all check their fields against this table (``check_range``, ``check_fields``),
with one message, e.g. ``grad_lr = -1.0 (--grad-lr): must be > 0.0``. This module imports nothing from
jaxtraffic: it is the lowest layer of ``learn`` (``learn.config`` imports ``learn.env`` and
``learn.gradient.config``, so they cannot import the config's checks).
"""

from __future__ import annotations

import dataclasses
from typing import Any

# name -> (lo, lo_inclusive, hi, hi_inclusive); None: unbounded on that side. A tuple's every element obeys it.
RULES: dict[str, tuple[float | None, bool, float | None, bool]] = {
    # plant
    "delay": (0.0, True, None, False), "alpha": (0.0, True, 1.0, True), "alpha_noise": (0.0, True, None, False),
    "n_points": (3, True, None, False), "dt": (0.0, False, None, False),
    "max_delay_steps": (0, True, 10**6, True),
    "substeps": (1, True, None, False), "filter_sigma": (0.0, True, None, False),
    "controller_points": (3, True, None, False),
    # env
    "horizon_s": (0.0, False, None, False), "delay_spread": (0.0, True, None, False),
    "phase_max": (0.0, True, None, False), "gain_max": (0.0, False, None, False),
    "gain_filter": (0.0, False, 1.0, True), "h_rate_weight": (0.0, True, None, False),
    "wave_weight": (0.0, True, None, False), "diverge_penalty": (0.0, True, None, False),
    "obs_segments": (0, True, None, False),
    # algo
    "num_envs": (1, True, None, False), "num_steps": (1, True, None, False), "update_epochs": (1, True, None, False),
    "num_minibatches": (1, True, None, False), "updates_per_chunk": (1, True, None, False),
    "lr": (0.0, False, None, False), "lr_decay_steps": (0.0, True, None, False), "lr_final": (0.0, True, 1.0, True),
    "gamma": (0.0, False, 1.0, True), "gae_lambda": (0.0, True, 1.0, True), "clip_eps": (0.0, False, None, False),
    "ent_coef": (0.0, True, None, False), "vf_coef": (0.0, True, None, False),
    "max_grad_norm": (0.0, False, None, False), "reward_scale": (0.0, False, None, False),
    "init_sigma": (0.0, False, None, False),
    # run
    "seed": (0, True, 2**32 - 1, True), "seeds": (1, True, None, False), "total_steps": (1, True, None, False),
    "max_wall_s": (0.0, False, None, False), "stop_patience": (1, True, None, False),
    "restart_steps": (0, True, None, False), "checkpoint_every": (1, True, None, False),
    "eval_horizon_s": (0.0, False, None, False), "val_horizon_s": (0.0, True, None, False),
    "val_target": (0.0, False, None, False),
    # grad (gradient-based training)
    "grad_steps": (1, True, None, False), "grad_lr": (0.0, False, None, False),
    "train_delays": (0.0, True, None, False), "train_alphas": (0.0, False, 1.0, True),
    "train_horizon_s": (0.0, False, None, False), "record_every": (1, True, None, False),
    "steps_per_chunk": (1, True, None, False), "reward_weight": (0.0, True, None, False),
    "waves_weight": (0.0, True, None, False), "comfort_weight": (0.0, True, None, False),
    "effort_weight": (0.0, True, None, False), "scenario_clip": (0.0, True, None, False),
    "certificate_weight": (0.0, True, None, False), "cem_population": (2, True, None, False),
    "cem_sigma": (0.0, False, None, False),
    "grad_gain_max": (0.0, False, None, False),
}


def flag(name: str) -> str:
    """The command-line flag of the field ``name``."""
    return "--" + name.replace("_", "-")


def fail(name: str, value: Any, why: str) -> ValueError:
    """The error of a bad value: ``name = value (--flag): why``."""
    return ValueError(f"{name} = {value!r} ({flag(name)}): {why}")


def range_text(rule: tuple) -> str:
    lo, lo_in, hi, hi_in = rule
    if hi is None:
        return f"must be {'>=' if lo_in else '>'} {lo}"
    return f"must lie in {'[' if lo_in else '('}{lo}, {hi}{']' if hi_in else ')'}"


def in_range(value: Any, rule: tuple) -> bool:
    lo, lo_in, hi, hi_in = rule
    ok = (value >= lo if lo_in else value > lo) if lo is not None else True
    return bool(ok and ((value <= hi if hi_in else value < hi) if hi is not None else True))


def check_range(name: str, value: Any) -> None:
    """``ValueError`` (``fail``) unless ``value`` (each element of a tuple or list) obeys ``RULES[name]``; a name
    without a rule, and ``None`` (unset), pass."""
    if name not in RULES or value is None:
        return
    for x in value if isinstance(value, (tuple, list)) else (value,):
        if not in_range(x, RULES[name]):
            raise fail(name, x, range_text(RULES[name]))


def check_fields(struct: Any, skip: tuple[str, ...] = ()) -> None:
    """``check_range`` of every field of the dataclass ``struct`` that has a rule (but those in ``skip``)."""
    for f in dataclasses.fields(struct):
        if f.name not in skip:
            check_range(f.name, getattr(struct, f.name))
