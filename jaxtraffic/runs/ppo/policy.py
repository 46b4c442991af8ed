"""A PPO run's saved policy: its arrays (``load_run``) and its controller (``load_ppo_policy``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_law import sigma_nodes
from jaxtraffic.control.gain_policy import feature_size, policy_controller
from jaxtraffic.io.files import from_jsonable, read_json
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.runs.checkpoint import BEST, CHECKPOINT, CONFIG, SUMMARY, load_best, load_checkpoint
from jaxtraffic.runs.config import TrainConfig

__all__ = ["SavedPolicy", "load_ppo_policy", "load_run"]


@dataclass
class SavedPolicy:
    """Per-seed policy arrays of a run (device axis dropped): flax ``params`` and
    observation statistics ``obs_mean`` / ``obs_var`` with a leading seed axis."""

    params: Any
    obs_mean: np.ndarray
    obs_var: np.ndarray


def load_run(run_dir: str | Path, checkpoint: str = "best") -> tuple[dict, SavedPolicy, dict]:
    """(config.json content, saved policy, summary or {}) of a run directory (``runs.config.load_config``
    turns the first into a ``TrainConfig``). ``checkpoint``: "best" (each member's best-scoring
    checkpoint, best.msgpack, when the run has one; else the last) or "last" (the state training
    stopped in, checkpoint.msgpack)."""
    if checkpoint not in ("best", "last"):
        raise ValueError(f"checkpoint must be 'best' or 'last', got {checkpoint!r}")
    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG
    if not cfg_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run directory (no {CONFIG})")
    config = read_json(cfg_path)
    summary_path = run_dir / SUMMARY
    summary = from_jsonable(read_json(summary_path)) if summary_path.exists() else {}
    if not isinstance(summary, dict):
        raise ValueError(f"{summary_path}: not a summary.json written by train.py")
    best = load_best(run_dir) if checkpoint == "best" else None
    if best is None and checkpoint == "best" and "best_val_score" in summary:
        raise ValueError(f"{run_dir / BEST} is missing, though {SUMMARY} says the run kept its best checkpoint: "
                         "restore it, or load the last state explicitly (checkpoint='last')")
    if best is not None and isinstance(summary.get("best_seed"), int) and "score" in best:
        chosen = int(np.argmin(np.asarray(best["score"])))  # the trainer's choice (runs.ppo.trainer)
        if summary["best_seed"] != chosen:
            raise ValueError(f"{summary_path}: best_seed = {summary['best_seed']}, but the scores in {run_dir / BEST} "
                             f"make member {chosen} the best (was the file edited?); pass seed= to choose a member")
    if best is not None:  # the best checkpoint of each member (the trainer's selection)
        policy = SavedPolicy(params=jax.tree.map(np.asarray, best["params"]), obs_mean=np.asarray(best["mean"]),
                             obs_var=np.asarray(best["var"]))
    else:
        runner, _ = load_checkpoint(run_dir)
        first = lambda x: np.asarray(x)[0]  # noqa: E731 - replicated across devices
        try:
            policy = SavedPolicy(params=jax.tree.map(first, runner["params"]),
                                 obs_mean=first(runner["stats"]["mean"]), obs_var=first(runner["stats"]["var"]))
        except (KeyError, IndexError, TypeError) as err:
            raise ValueError(f"{run_dir / CHECKPOINT}: no policy in the saved state "
                             f"({type(err).__name__}: {err})") from None
    return config, policy, summary


def load_ppo_policy(run_dir: Path, config: TrainConfig, seed: int | None = None,
                    checkpoint: str = "best") -> Controller:
    """The deterministic policy controller of a PPO run directory, member ``seed`` (default: the best,
    ``best_seed`` of summary.json, else 0), on its training grid; ``checkpoint`` as for ``load_run``."""
    _, saved, summary = load_run(run_dir, checkpoint)
    if seed is None:
        seed = summary.get("best_seed", 0) if summary else 0
        if not isinstance(seed, int):
            raise ValueError(f"{run_dir / SUMMARY}: best_seed = {seed!r} is not an integer")
    n_seeds = saved.obs_mean.shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"seed {seed} not in run with {n_seeds} seeds")
    segments = config.env.obs_segments
    expected = feature_size(config.plant.n_points, segments)
    got = saved.obs_mean.shape[-1]
    if got != expected:  # (a run from before the applied gains is recognised by its config.json, see config)
        raise ValueError(f"{run_dir}: {CONFIG} says n_points = {config.plant.n_points}, obs_segments = {segments} (an "
                         f"observation of {expected} values) but the checkpoint holds an observation of {got} values"
                         + (f" ({got // 3 - 1} per field)" if got % 3 == 0 else "")
                         + ": the two files do not belong together")
    dx = float(TrafficParams().L) / (config.plant.n_points - 1)  # the training road (runs.config has no length)
    return policy_controller(
        jax.tree.map(lambda x: jnp.asarray(x[seed]), saved.params), saved.obs_mean[seed], saved.obs_var[seed],
        config.env.gain_max, hidden=tuple(config.ppo.hidden), init_sigma=config.ppo.init_sigma,
        gain_filter=config.env.gain_filter, obs_segments=segments,
        sigma_nodes=sigma_nodes(config.env.filter_sigma, dx))
