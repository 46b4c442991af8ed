"""The main job's runs as data (``paper.recipes``) and a run's config as TOML (``runs.config.toml``)."""

from __future__ import annotations

import math

import pytest

from jaxtraffic.cli.train import config_from_args
from jaxtraffic.paper.recipes import NAMES, recipe, training_plant
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.toml import config_from_toml, config_toml, read_config, write_config

# the command lines the main job ran before its runs were data: each recipe must describe the same run
COMMAND_LINES = {
    "ppo": ["--out-dir", "runs/default", "--max-wall-s", "600"],
    "gradient-gains": ["--algo", "gradient", "--policy", "gains", "--out-dir", "runs/gradient-gains"],
    "gradient-network": ["--algo", "gradient", "--policy", "network", "--out-dir", "runs/gradient-network"],
    "gradient-robust": ["--algo", "gradient", "--policy", "schedule", "--out-dir", "runs/gradient-robust"],
}
PLANT_FLAGS = {"reference": ["--n-points", "801", "--scheme", "muscl", "--substeps", "2", "--controller-points", "201"],
               "half": ["--n-points", "401", "--scheme", "muscl", "--controller-points", "201"]}


@pytest.mark.parametrize("name", NAMES)
def test_each_recipe_is_the_run_its_command_line_described(name):
    plant = {"gradient-gains": "reference", "gradient-network": "reference", "gradient-robust": "half"}.get(name)
    argv = COMMAND_LINES[name] + (PLANT_FLAGS[plant] if plant else [])
    assert recipe(name) == config_from_args(argv)
    if plant:  # evaluate.py's plant for the recipe: the same fields the flags set
        fields = training_plant(plant, 201, (801, 2))
        assert recipe(name).replace(**fields) == recipe(name)


def test_an_unknown_recipe_is_refused():
    with pytest.raises(ValueError, match="no recipe 'ppo2'"):
        recipe("ppo2")


@pytest.mark.parametrize("config", [
    TrainConfig(),
    TrainConfig.from_flat(algo="gradient", policy="schedule", n_points=21, train_delays=(0.5, 1.5), grad_lr=0.02),
    TrainConfig.from_flat(min_wave_speed=None, max_wall_s=math.inf, gain_max=(1.0, 2.0, 3.0), tensorboard="tb"),
])
def test_a_config_survives_toml(config, tmp_path):
    assert config_from_toml(config_toml(config)) == config
    write_config(config, tmp_path / "c.toml")
    assert read_config(tmp_path / "c.toml") == config


@pytest.mark.parametrize("text, match", [
    ("version = 2\n[plant]\nn_points = 2\n", r"c.toml: n_points = 2"),
    ("version = 2\n[plant]\nnpoints = 21\n", r"unknown field\(s\) \['npoints'\] in \[plant\]"),
    ("version = 2\n[plants]\n", r"unknown section\(s\) \['plants'\]"),
    ("version = 1\n", "configuration version 1"),
    ("version = 2\n[plant\n", "not valid TOML"),
    ("version = 2\n[run]\nmax_wall_s = nan\n", "max_wall_s = nan"),
])
def test_a_bad_file_is_one_clear_error(text, match, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_config(path)
