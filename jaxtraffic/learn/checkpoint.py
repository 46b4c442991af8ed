"""Atomic, pickle-free checkpoints (flax msgpack serialization), run-directory I/O, ``load_policy``.

A checkpoint file holds ``{"runner": <state dict of the PPO Runner>, "meta": <progress>}``.
Every write goes to a temporary file in the same directory, is flushed and fsynced, then
``os.replace``d over the target, so an interruption never leaves a half-written file.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_policy import feature_size, policy_controller
from jaxtraffic.learn.config import TrainConfig, load_config

CHECKPOINT = "checkpoint.msgpack"
CONFIG = "config.json"
SUMMARY = "summary.json"


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def to_jsonable(x: Any) -> Any:
    """Convert numpy/jax scalars and arrays to JSON types; non-finite floats become None."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        return to_jsonable(np.asarray(x).tolist())
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def write_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(to_jsonable(obj), indent=2, sort_keys=False) + "\n")


def save_checkpoint(run_dir: str | Path, runner: Any, meta: dict) -> None:
    """Write the runner (all devices and seeds) and the progress ``meta`` atomically."""
    state = {"runner": serialization.to_state_dict(jax.device_get(runner)), "meta": to_jsonable(meta)}
    atomic_write_bytes(Path(run_dir) / CHECKPOINT, serialization.msgpack_serialize(state))


def load_checkpoint(run_dir: str | Path) -> tuple[dict, dict]:
    """(runner state dict, meta) of ``run_dir``'s checkpoint."""
    path = Path(run_dir) / CHECKPOINT
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    state = serialization.msgpack_restore(path.read_bytes())
    return state["runner"], state["meta"]


def restore_runner(template: Any, state: dict) -> Any:
    """Fill ``template`` (a Runner of the right structure) with a loaded state dict."""
    return serialization.from_state_dict(template, state)


@dataclass
class SavedPolicy:
    """Per-seed policy arrays of a run (device axis dropped): flax ``params`` and
    observation statistics ``obs_mean`` / ``obs_var`` with a leading seed axis."""

    params: Any
    obs_mean: np.ndarray
    obs_var: np.ndarray


def load_run(run_dir: str | Path) -> tuple[dict, SavedPolicy, dict]:
    """(config.json content, saved policy, summary or {}) of a run directory (``learn.config.load_config``
    turns the first into a ``TrainConfig``)."""
    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG
    if not cfg_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run directory (no {CONFIG})")
    config = json.loads(cfg_path.read_text())
    runner, _ = load_checkpoint(run_dir)
    first = lambda x: np.asarray(x)[0]  # noqa: E731 - replicated across devices
    policy = SavedPolicy(params=jax.tree.map(first, runner["params"]),
                         obs_mean=first(runner["stats"]["mean"]), obs_var=first(runner["stats"]["var"]))
    summary_path = run_dir / SUMMARY
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    return config, policy, summary


def load_policy(run_dir: str | Path, seed: int | None = None) -> tuple[Controller, TrainConfig]:
    """Controller and ``TrainConfig`` of a run directory written by ``train.py``.

    ``seed`` selects one of the run's seeds (default: the best one by final evaluation reward,
    as recorded in ``summary.json``, else 0). A run trained by gradient (``"algo": "gradient"`` in
    its config.json) loads through ``gradient_trainer.load_gradient_run``.
    """
    run_dir = Path(run_dir)
    config = load_config(run_dir)
    if config.run.algo == "gradient":
        from jaxtraffic.learn.gradient_trainer import load_gradient_policy  # it imports this module

        return load_gradient_policy(run_dir, config), config
    _, saved, summary = load_run(run_dir)
    if seed is None:
        seed = int(summary.get("best_seed", 0)) if summary else 0
    n_seeds = saved.obs_mean.shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"seed {seed} not in run with {n_seeds} seeds")
    expected = feature_size(config.plant.n_points)
    if saved.obs_mean.shape[-1] != expected:
        raise ValueError(f"{run_dir} was written by an older jaxtraffic (observation of {saved.obs_mean.shape[-1]} "
                         f"values, expected {expected} with the applied gains): retrain it with train.py")
    controller = policy_controller(
        jax.tree.map(lambda x: jnp.asarray(x[seed]), saved.params), saved.obs_mean[seed], saved.obs_var[seed],
        config.env.gain_max, hidden=config.algo.hidden(), init_sigma=config.algo.init_sigma,
        gain_filter=config.env.gain_filter)
    return controller, config
