"""SB3 VecNormalize statistics exported as JSON (no pickle), applied to a policy, and the evidence check."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from jaxtraffic.ecosystem.normalization import (
    export_obs_normalization,
    load_obs_normalization,
    normalization_evidence,
    normalized_policy,
)


def _fake_vecnormalize():
    rms = SimpleNamespace(mean=np.array([1.0, -2.0, 0.5]), var=np.array([4.0, 0.25, 1.0]))
    return SimpleNamespace(obs_rms=rms, clip_obs=3.0, epsilon=1e-8, norm_obs=True)


def test_round_trip_and_apply(tmp_path):
    path = export_obs_normalization(_fake_vecnormalize(), tmp_path / "stats.json")
    stats = load_obs_normalization(path)
    out = normalized_policy(lambda o: o, stats)(np.array([3.0, -2.0, 100.0]))
    np.testing.assert_allclose(out, [1.0, 0.0, 3.0], rtol=1e-6)  # (3-1)/2, 0, clipped at 3


def test_not_normalised_is_identity(tmp_path):
    vn = _fake_vecnormalize()
    vn.norm_obs = False
    stats = load_obs_normalization(export_obs_normalization(vn, tmp_path / "s.json"))
    fn = lambda o: o  # noqa: E731
    assert stats is None and normalized_policy(fn, stats) is fn


def test_bad_file_named(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "x"}))
    with pytest.raises(ValueError, match="bad.json"):
        load_obs_normalization(bad)


def test_evidence(tmp_path):
    model = tmp_path / "ppo.zip"
    model.write_bytes(b"")
    assert normalization_evidence(model) is None
    (tmp_path / "VecNormalize_stats.pkl").write_bytes(b"")
    assert normalization_evidence(model).name == "VecNormalize_stats.pkl"


def test_real_vecnormalize(tmp_path):
    vec_env = pytest.importorskip("stable_baselines3.common.vec_env")
    from jaxtraffic.ecosystem.sb3 import SB3VecEnv

    venv = vec_env.VecNormalize(SB3VecEnv(num_envs=2, n_points=21, horizon_s=2.0), norm_reward=False)
    venv.reset()
    for _ in range(3):
        venv.step(np.zeros((2, 3), dtype=np.float32))
    stats = load_obs_normalization(export_obs_normalization(venv, tmp_path / "s.json"))
    raw = venv.get_original_obs()
    np.testing.assert_allclose(stats(raw), venv.normalize_obs(raw), rtol=1e-5, atol=1e-5)
