"""A gradient- or CEM-trained run's saved controller (``load_gradient_policy``) and the settings a
``TrainConfig`` gives the algorithm (``gradient_setup``)."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
from flax import serialization

from jaxtraffic.control.base import Controller
from jaxtraffic.learn.gradient import objective
from jaxtraffic.learn.gradient.config import GradientConfig
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig

__all__ = ["gradient_setup", "load_gradient_policy", "own_grid_controller"]


def gradient_setup(config: TrainConfig) -> tuple[GradientConfig, TrafficParams]:
    """The algorithm's settings and the nominal plant (no alpha noise) of a ``TrainConfig`` with
    ``run.algo = "gradient"``."""
    nominal = config.plant.replace(alpha_noise=0.0)
    return config.grad, nominal


def own_grid_controller(theta, grad_config: GradientConfig, plant: TrafficParams, delay) -> Controller:
    """The controller of parameters ``theta`` on its own grid (``controller_points`` nodes, default the plant's),
    told the delay ``delay`` (s)."""
    n = grad_config.controller_points or plant.n_points
    return objective.own_controller(theta, grad_config, n, objective.ROAD_LENGTH / (n - 1), delay)


def load_gradient_policy(run_dir: str | Path, config: TrainConfig, seed: int | None = None,
                         checkpoint: str = "best") -> Controller:
    """The controller saved in a gradient-trained run directory (``config``: its ``load_config``), on its own
    grid (``runs.policy.policy_grid``). ``seed`` and ``checkpoint`` are accepted for ``runs.policy.LOADERS``'
    common signature and ignored: such a run has one policy, its last state."""
    grad_config, plant = gradient_setup(config)
    state, _ = ckpt.load_checkpoint(run_dir)
    template = objective.init_theta(grad_config, plant, jax.random.PRNGKey(0))
    theta = serialization.from_state_dict(template, state["theta"])
    return own_grid_controller(jax.tree.map(jnp.asarray, theta), grad_config, plant, config.plant.delay)
