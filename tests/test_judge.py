"""``evaluate.py --judge``: your policy against the baselines on both plants, no training (tiny settings)."""

from __future__ import annotations

import json

import pytest
from tiny_runs import REPO

import evaluate

TINY = ["--horizon", "1", "--noise-seeds", "1", "--n-points", "11", "--reference-grid", "15x1"]
SPEC = f"mine={REPO / 'tests' / 'judge_controller.py'}:soft_lyapunov"


def test_judge_without_training(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # runs/ would be created here by a training
    out = tmp_path / "judged"
    result = evaluate.main(["--judge", "--controller", SPEC, "--out", str(out), *TINY])
    assert not (tmp_path / "runs").exists()
    assert set(result["plants"]) == {"paper", "reference"}
    for plant in ("paper", "reference"):
        delay4 = result["plants"][plant]["scenarios"]["delay4"]
        assert {"open_loop", "lyapunov", "backstepping", "mine"} <= set(delay4) and "ppo" not in delay4
    assert json.loads((out / "judge.json").read_text())["meta"]["controllers"] == ["mine"]
    report = (out / "REPORT.md").read_text()
    assert "| delay4 | mine |" in report and "| delay4 | backstepping |" in report


def test_judge_needs_controller(tmp_path):
    with pytest.raises(SystemExit) as err:
        evaluate.main(["--judge", "--out", str(tmp_path / "o"), *TINY])
    assert err.value.code == 2
