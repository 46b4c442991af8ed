"""Observation statistics of SB3's ``VecNormalize``, exported without pickle, and applied to a policy.

A policy trained under ``VecNormalize`` sees ``clip((obs - mean) / sqrt(var + epsilon), -clip, clip)``; judged on
raw observations it acts on inputs it never saw. The project loads no pickle a user hands it, so the statistics
travel as JSON: ``export_obs_normalization(vec_normalize, "stats.json")`` in the training script, then
``normalized_policy(fn, load_obs_normalization("stats.json"))`` (or ``evaluate.py --controller`` code doing so).
``normalization_evidence(model_zip)`` names the sign that a policy was trained normalised (a ``vecnormalize*.pkl``
next to its .zip), so a loader can refuse instead of judging it silently on unnormalised observations.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from jaxtraffic.io.files import atomic_write_text, read_text

__all__ = ["ObsNormalization", "active", "applying", "export_obs_normalization", "load_obs_normalization",
           "normalization_evidence", "normalized_policy"]
FORMAT = "jaxtraffic.obs_normalization/1"


@dataclass(frozen=True)
class ObsNormalization:
    """VecNormalize's observation statistics: running mean and variance, clip bound and epsilon."""

    mean: np.ndarray
    var: np.ndarray
    clip: float
    epsilon: float

    def __call__(self, obs: Any) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        return np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip, self.clip).astype(np.float32)


def export_obs_normalization(vec_normalize: Any, path: str | Path) -> Path:
    """Write ``vec_normalize``'s (SB3 ``VecNormalize``) observation statistics to ``path`` as JSON."""
    rms = vec_normalize.obs_rms
    if isinstance(rms, dict):
        raise ValueError("VecNormalize over a dict observation space: not supported (GainEnv's is a Box)")
    doc = {"format": FORMAT, "mean": np.asarray(rms.mean, dtype=float).tolist(),
           "var": np.asarray(rms.var, dtype=float).tolist(), "clip": float(vec_normalize.clip_obs),
           "epsilon": float(vec_normalize.epsilon), "norm_obs": bool(vec_normalize.norm_obs)}
    path = Path(path)
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    return path


def load_obs_normalization(path: str | Path) -> ObsNormalization | None:
    """The statistics ``export_obs_normalization`` wrote (None when the training did not normalise
    observations, ``norm_obs`` false); ``ValueError`` naming the file for anything else."""
    path = Path(path)
    try:
        doc = json.loads(read_text(path))
        if doc.get("format") != FORMAT:
            raise ValueError(f"format {doc.get('format')!r}, expected {FORMAT!r}")
        mean, var = np.asarray(doc["mean"], dtype=float), np.asarray(doc["var"], dtype=float)
        clip, eps = float(doc["clip"]), float(doc["epsilon"])
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError, ValueError) as err:
        raise ValueError(f"{path}: not an observation-normalisation file (jaxtraffic.ecosystem."
                         f"export_obs_normalization): {err}") from None
    if mean.shape != var.shape or mean.ndim != 1 or not (np.all(np.isfinite(mean)) and np.all(var >= 0)) \
            or not clip > 0 or not eps >= 0:
        raise ValueError(f"{path}: inconsistent statistics (mean/var shapes {mean.shape}/{var.shape}, "
                         f"clip {clip}, epsilon {eps})")
    return ObsNormalization(mean, var, clip, eps) if doc.get("norm_obs", True) else None


_ACTIVE: list[ObsNormalization] = []  # set by ``applying`` while evaluate.py builds a --controller


def normalized_policy(fn: Callable[[Any], Any], stats: ObsNormalization | None) -> Callable[[Any], Any]:
    """``fn`` fed the normalised observation (``fn`` itself when ``stats`` is None)."""
    if stats is None:
        return fn
    return lambda obs: fn(stats(obs))


def normalization_evidence(model_path: str | Path) -> Path | None:
    """A ``vecnormalize*.pkl`` (any case) next to the SB3 model ``model_path``: the sign it was trained under
    ``VecNormalize``; None when there is none."""
    folder = Path(model_path).parent
    found = sorted(p for p in folder.glob("*") if p.is_file() and p.suffix.lower() == ".pkl"
                   and p.name.lower().startswith("vecnormalize")) if folder.is_dir() else []
    return found[0] if found else None


@contextmanager
def applying(stats: ObsNormalization | None) -> Iterator[None]:
    """While it lasts, ``ecosystem.policy_as_controller`` feeds its policy ``stats``-normalised observations
    (``evaluate.py --controller-normalization``: the statistics reach the user's bridge code unchanged)."""
    if stats is None:
        yield
        return
    _ACTIVE.append(stats)
    try:
        yield
    finally:
        _ACTIVE.pop()


def active() -> ObsNormalization | None:
    """The statistics ``applying`` set, else None."""
    return _ACTIVE[-1] if _ACTIVE else None
