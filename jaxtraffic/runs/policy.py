"""A trained run's controller, whatever the algorithm that trained it: ``load_policy`` dispatches on the run's
``algo`` to the algorithm's own loader (``ppo.policy``, ``gradient.policy``); ``policy_grid`` and
``policy_certificate`` describe the controller on its own grid."""

from __future__ import annotations

import numbers
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxtraffic.control.adapter import ControllerGrid, adapt
from jaxtraffic.control.base import Controller
from jaxtraffic.control.stability import certify_controller
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.runs.checkpoint import (
    BEST,
    CHECKPOINT,
    CONFIG,
    PROBLEM,
    check_problem,
    load_best,
    load_checkpoint,
)
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.gradient.policy import load_gradient_policy
from jaxtraffic.runs.ppo.policy import load_ppo_policy

__all__ = ["LOADERS", "load_policy", "policy_certificate", "policy_grid"]

LOADERS = {"ppo": load_ppo_policy, "gradient": load_gradient_policy}  # run.algo -> (run_dir, config, seed, checkpoint)


def policy_grid(config: TrainConfig) -> ControllerGrid:
    """The grid a run's controller acts on: ``controller_points`` nodes (default the training plant's),
    period dt, the training plant's delay buffer."""
    pl = config.plant
    return ControllerGrid(n_points=config.grad.controller_points or pl.n_points, dt=float(pl.dt),
                          max_delay_steps=pl.max_delay_steps)


def policy_certificate(controller: Controller, config: TrainConfig) -> dict[str, Any]:
    """The stability certificate (``control.stability``) of a run's controller on its own grid, at its
    training plant's nominal delay and alpha, as a JSON-ready dict."""
    grid = policy_grid(config)
    nominal = config.plant.replace(n_points=grid.n_points, substeps=1, scheme="upwind", alpha_noise=0.0)
    return certify_controller(controller, nominal, float(config.plant.delay), config.env.filter_sigma).to_json()


def load_policy(run_dir: str | Path, seed: int | None = None, checkpoint: str = "best",
                plant: TrafficParams | None = None) -> tuple[Controller, TrainConfig]:
    """Controller and ``TrainConfig`` of a run directory written by ``train.py``.

    The controller acts on its own grid (``policy_grid(config)``: the training plant's, or the
    gradient trainer's ``controller_points``); with ``plant`` (concrete ``TrafficParams`` whose grid
    and step refine it by integers) it is adapted to act on that plant's discretisation
    (``control.adapter.adapt``: restricted observation, interpolated and held time gap).

    ``checkpoint``: "best" (default: the best-scoring checkpoint of each member, which the PPO
    trainer keeps in best.msgpack) or "last" (the state training stopped in). ``seed`` selects one
    of the run's members (default: the best one, ``best_seed`` of ``summary.json``, else 0). A run
    trained by gradient (``"algo": "gradient"`` in its config.json) loads through
    ``gradient.policy.load_gradient_policy``.
    """
    if checkpoint not in ("best", "last"):
        raise ValueError(f"checkpoint must be 'best' or 'last', got {checkpoint!r}")
    if seed is not None and (not isinstance(seed, numbers.Integral) or isinstance(seed, bool) or seed < 0):
        raise ValueError(f"seed must be None (the run's best member) or an int >= 0, got {seed!r}")
    if plant is not None and (not isinstance(plant, TrafficParams) or any(
            np.ndim(x) for x in jax.tree_util.tree_leaves(plant))):
        raise ValueError("plant must be one concrete TrafficParams (not a batch from stack_params): the controller is "
                         "adapted to one plant's grid; adapt it once and batch the plants in simulate_batch")
    run_dir = Path(run_dir)
    config = load_config(run_dir)
    best = run_dir / BEST
    if checkpoint == "best" and (saved_best := load_best(run_dir)) is not None:  # (None: no best.msgpack)
        check_problem(config, saved_best.get(PROBLEM), best)
    if (run_dir / CHECKPOINT).exists():
        check_problem(config, load_checkpoint(run_dir)[1].get(PROBLEM), run_dir / CHECKPOINT)
    try:
        load = LOADERS[config.run.algo]
        controller = load(run_dir, config, seed, checkpoint)
    except (KeyError, AttributeError, TypeError, IndexError) as err:  # e.g. config.json's algo or policy edited
        raise ValueError(f"{run_dir}: {CONFIG} (algo {config.run.algo}, policy {config.grad.policy}) and the "
                         f"checkpoint do not belong together ({type(err).__name__}: {err})") from None
    return (controller if plant is None else adapt(controller, policy_grid(config), plant)), config
