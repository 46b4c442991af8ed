"""benchmarks/tune_baselines.py --plant training: the baselines are tuned on the plant the CEM-trained learned laws
train on (both CEM recipes' grid and scheme), acting on the paper's grid as those laws do."""

from __future__ import annotations

import sys
from pathlib import Path

import jaxtraffic as jt
from jaxtraffic.control.adapter import PAPER_GRID, baseline_grid
from jaxtraffic.paper.recipes import recipe

ROOT = Path(__file__).resolve().parents[1]


def test_the_training_plant_is_every_cem_recipe_s_and_the_baselines_act_on_the_paper_grid():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import tune_baselines

    assert tune_baselines.plant("paper") == jt.TrafficParams()
    trained_on = tune_baselines.plant("training")
    for name in ("adaptive-residual", "gradient-robust"):  # the two CEM-trained laws
        cem = recipe(name)
        assert cem.grad.grad_method == "cem"
        for field in tune_baselines.GRID_FIELDS:
            assert getattr(trained_on, field) == getattr(cem.plant, field), (name, field)
        assert cem.grad.controller_points == PAPER_GRID.n_points  # their controllers act on the paper's grid
    assert (trained_on.n_points, trained_on.scheme) == (401, "muscl")
    assert baseline_grid(trained_on) == PAPER_GRID  # and so do the baselines tuned there
    # everything else (the physics, the delay the scenarios set) is the paper grid's default
    assert trained_on.replace(n_points=201, scheme="upwind") == jt.TrafficParams()
