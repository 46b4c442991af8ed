"""The main job's runs as data (``paper.recipes``): each recipe is the run its old command line described."""

from __future__ import annotations

from importlib import resources

import pytest

from jaxtraffic.cli.train import config_from_args
from jaxtraffic.paper.recipes import NAMES, recipe, training_plant

# the command lines the main job ran before its runs were data: each recipe must describe the same run
COMMAND_LINES = {
    "ppo": ["--out-dir", "runs/default", "--max-wall-s", "600"],
    "gradient-gains": ["gradient", "--policy", "gains", "--out-dir", "runs/gradient-gains"],
    "gradient-network": ["gradient", "--policy", "network", "--out-dir", "runs/gradient-network"],
    "gradient-robust": ["gradient", "--policy", "schedule", "--out-dir", "runs/gradient-robust"],
    "adaptive-residual": ["gradient", "--policy", "residual", "--out-dir", "runs/adaptive-residual"],
}
PLANT_FLAGS = {"reference": ["--n-points", "801", "--scheme", "muscl", "--substeps", "2", "--controller-points", "201"],
               "half": ["--n-points", "401", "--scheme", "muscl", "--controller-points", "201"]}


@pytest.mark.parametrize("name", NAMES)
def test_each_recipe_is_the_run_its_command_line_described(name):
    plant = {"gradient-gains": "reference", "gradient-network": "reference", "gradient-robust": "half",
             "adaptive-residual": "half"}.get(name)
    argv = COMMAND_LINES[name] + (PLANT_FLAGS[plant] if plant else [])
    assert recipe(name) == config_from_args(argv)
    if plant:  # evaluate.py's plant for the recipe: the same fields the flags set
        fields = training_plant(plant, 201, (801, 2))
        assert recipe(name).updated(**fields) == recipe(name)


def test_an_unknown_recipe_is_refused():
    with pytest.raises(ValueError, match="no recipe 'ppo2'"):
        recipe("ppo2")


@pytest.mark.parametrize("name", NAMES)
def test_each_recipe_file_is_a_config_file_of_train_py(name):
    """``train.py [ALGO] --config RECIPE.toml`` is the recipe, with and without the subcommand (a gradient
    recipe's fields are no valid PPO run: the other subcommand's defaults must not be built from them)."""
    with resources.as_file(resources.files("jaxtraffic.paper.recipes").joinpath(f"{name}.toml")) as path:
        algo = recipe(name).run.algo
        assert config_from_args(["--config", str(path)]) == recipe(name)
        assert config_from_args([algo, "--config", str(path)]) == recipe(name)
        assert config_from_args([algo, "--config", str(path), "--seed", "3"]) == recipe(name).updated(run={"seed": 3})
