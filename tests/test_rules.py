"""One name per hyperparameter, from the flag to the code, and one range per field (``jaxtraffic.fields``)."""

from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

import jaxtraffic
from jaxtraffic import fields
from jaxtraffic.learn.env import make_env_params
from jaxtraffic.learn.gradient.config import POLICY_DEFAULTS, GradientConfig
from jaxtraffic.learn.gradient.objective import Weights, weights_of
from jaxtraffic.learn.ppo import PPOConfig, check_ppo_config
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.tree import SECTIONS, leaf_fields
from jaxtraffic.runs.gradient.policy import gradient_setup

# a value of each gradient field other than its default and every policy's default, valid for the gains policy
GIVEN = {"grad_steps": 6, "grad_lr": 0.02, "train_delays": (1.0, 2.0), "train_alphas": (0.2, 0.3),
         "train_amplitudes": (5.0,), "train_wavenumbers": (2, 3), "train_phases": (0.5,), "train_horizon_s": 90.0,
         "record_every": 3, "steps_per_chunk": 2, "reward_weight": 0.5, "waves_weight": 0.25, "comfort_weight": 2e-5,
         "scenario_clip": 0.75, "init_gains": (0.1, -0.2, 0.3),
         "schedule_knots": (0.0, 3.0), "grad_method": "cem", "cem_population": 5, "cem_sigma": 0.4,
         "grad_gain_max": 2.5, "controller_points": 11, "cem_tie_weight": 0.05, "residual_alpha_floor": 0.2,
         "cem_fitness": "mean_l2"}
TREE_FIELDS = {f.name for s in SECTIONS for f in leaf_fields(s)}


def test_every_flag_reaches_the_algorithm_under_its_own_name():
    assert set(GIVEN) == {f.name for f in leaf_fields("grad")} - {"policy"}
    cfg = gradient_setup(TrainConfig.make(run={"algo": "gradient"}, grad=GIVEN))[0]
    assert {name: getattr(cfg, name) for name in GIVEN} == GIVEN
    # the fields the algorithm has beyond the flags of its section come from the environment and the network
    tree = TrainConfig.make(run={"algo": "gradient"}, plant={"n_points": 21}, grad={"controller_points": 11},
                            env={"gain_filter": 0.5, "filter_sigma": 10.0, "train_split": 3,
                                 "train_sensor_noise": (0.0, 0.05)})
    cfg = gradient_setup(tree)[0]
    assert (cfg.gain_filter, cfg.filter_sigma, cfg.controller_points, cfg.hidden, cfg.train_split,
            cfg.train_sensor_noise) == (0.5, 10.0, 11, tuple(tree.ppo.hidden), 3, (0.0, 0.05))
    extra = {f.name for f in dataclasses.fields(GradientConfig)} - set(GIVEN) - {"policy"}
    assert extra == {"hidden", "gain_filter", "filter_sigma", "max_grad_norm", "train_split", "train_sensor_noise"}
    # the policies' defaults and the objective's weights use the same names
    assert all(set(d) <= set(GIVEN) for d in POLICY_DEFAULTS.values())
    assert {f.name for f in dataclasses.fields(Weights)} <= set(GIVEN)
    w = weights_of(cfg)
    assert all(getattr(w, f.name) == np.float32(getattr(cfg, f.name)) for f in dataclasses.fields(Weights))


def test_every_range_lives_in_a_field_and_fields_imports_no_jaxtraffic():
    """The tree's fields that configure a library field carry that field's range (one home), and the helper
    module sits below everything it serves."""
    from jaxtraffic.learn.env import EnvParams
    from jaxtraffic.learn.env_config import EnvConfig

    assert SECTIONS["env"] is EnvConfig and SECTIONS["plant"] is jaxtraffic.TrafficParams  # no mirror classes
    shared = {f.name for f in dataclasses.fields(EnvParams)} & {f.name for f in dataclasses.fields(EnvConfig)}
    assert shared and all(fields.range_of(EnvParams, n) is None for n in shared)  # the range is EnvConfig's alone
    for name in shared:
        assert getattr(EnvParams(), name) == getattr(EnvConfig(), name), name  # one default
        rule = fields.range_of(EnvConfig, name)
        if rule is not None and rule[0] is not None:  # the struct is checked against EnvConfig's range
            with pytest.raises(ValueError, match=rf"{name} = "):
                make_env_params(**{name: rule[0] - 1.0})
    tree = ast.parse(Path(fields.__file__).read_text())
    imported = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)] + \
        [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in imported if m and m.split(".")[0] == "jaxtraffic"], imported


# one bad value: the config tree and the struct that uses the field reject it with the same message
@pytest.mark.parametrize("name, value, struct", [
    ("gain_filter", 1.5, lambda v: make_env_params(gain_filter=v)),
    ("gain_filter", 0.0, lambda v: GradientConfig(gain_filter=v)),
    ("wave_weight", -1.0, lambda v: make_env_params(wave_weight=v)),
    ("gain_max", 0.0, lambda v: make_env_params(gain_max=(1.0, v, 3.0))),
    ("clip_eps", 0.0, lambda v: check_ppo_config(PPOConfig(clip_eps=v))),
    ("gamma", 0.0, lambda v: check_ppo_config(PPOConfig(gamma=v))),
    ("grad_lr", -1.0, lambda v: GradientConfig(grad_lr=v)),
    ("waves_weight", -0.5, lambda v: GradientConfig(waves_weight=v)),
    ("grad_steps", 0, lambda v: GradientConfig(grad_steps=v)),
    ("train_delays", -1.0, lambda v: GradientConfig(train_delays=(2.0, v))),
    ("train_alphas", 0.0, lambda v: GradientConfig(train_alphas=(v,))),
    ("cem_population", 1, lambda v: GradientConfig(cem_population=v)),
])
def test_one_rule_checked_by_the_tree_and_by_the_struct(name, value, struct):
    lib = {"gamma": PPOConfig, "clip_eps": PPOConfig, "gain_filter": GradientConfig}.get(name, GradientConfig)
    from jaxtraffic.learn.env_config import EnvConfig

    lib = EnvConfig if name in ("wave_weight", "gain_max") else lib
    rule = fields.range_of(lib, name)
    assert rule is not None and not fields.in_range(value, rule)
    message = re.escape(f"{name} = {value!r}: {fields.range_text(rule)}")
    given = {name: (1.0, value, 3.0) if name == "gain_max" else (2.0, value) if name == "train_delays"
             else (value,) if name == "train_alphas" else value}
    section = next(s for s in SECTIONS if name in {f.name for f in leaf_fields(s)})
    with pytest.raises(ValueError, match=message):
        TrainConfig.make(**{section: given, "run": {"algo": "gradient"}})
    with pytest.raises(ValueError, match=message):
        struct(value)


def test_the_plants_own_grid_is_not_a_grid_of_its_own():
    """GradientConfig's controller_points 0 (the tree's None: the plant's grid) passes; 1 or 2 points do not."""
    assert GradientConfig(controller_points=0).controller_points == 0
    with pytest.raises(ValueError, match=r"controller_points = 2: must be >= 3"):
        GradientConfig(controller_points=2)
