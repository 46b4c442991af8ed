"""The speed anchor (benchmarks/c_kernel.py, issue 48.2: the default closed loop as a C kernel, checked against
``simulate_batch``) and the results comparison's tolerances (benchmarks/compare_results.py: floats to a relative
tolerance, counts exactly)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import compare_results  # noqa: E402  (benchmarks/compare_results.py)


def _tree(tmp_path: Path, name: str, data: dict) -> Path:
    d = tmp_path / name
    d.mkdir()
    (d / "robustness.json").write_text(json.dumps(data))
    return d


def test_compare_results_accepts_rounding_and_refuses_moved_counts(tmp_path, capsys):
    base = {"rows": {"lyapunov": {"stabilised": 41, "diverged": 13}}, "J": [1.0e4, 2.5], "flag": [True, False],
            "wall_s": 3.0}
    rounded = {"rows": {"lyapunov": {"stabilised": 41, "diverged": 13}}, "J": [1.0e4 * (1 + 3e-6), 2.5],
               "flag": [True, False], "wall_s": 9.0}  # a clock reading is skipped
    a, b = _tree(tmp_path, "a", base), _tree(tmp_path, "b", rounded)
    assert compare_results.main([str(a), str(b)]) == 0
    assert "1 floats within it" in capsys.readouterr().out
    assert compare_results.main([str(a), str(b), "--exact"]) == 1
    assert compare_results.main([str(a), str(b), "--rtol", "1e-6"]) == 1
    moved = json.loads(json.dumps(rounded))
    moved["rows"]["lyapunov"]["stabilised"] = 42  # a map count: exactly, at any tolerance
    c = _tree(tmp_path, "c", moved)
    assert compare_results.main([str(a), str(c), "--rtol", "0.5"]) == 1
    assert compare_results.differences(base, moved, rtol=0.5) == [("/rows/lyapunov/stabilised", 41, 42)]
    flipped = {**base, "flag": [True, True]}
    assert compare_results.differences(base, flipped, rtol=1.0) == [("/flag[1]", False, True)]


def test_float_tolerance_edges():
    c = compare_results.Comparison(rtol=1e-5)
    assert compare_results.compare(float("nan"), float("nan"), c).beyond == []
    assert compare_results.compare(float("inf"), 1e308, c).beyond != []
    assert compare_results.compare(0.0, 1e-30, compare_results.Comparison(rtol=1e-5)).beyond != []
    assert compare_results.compare(0.0, 1e-30, compare_results.Comparison(rtol=1e-5, atol=1e-20)).beyond == []
    assert compare_results.compare(1, 1.0, compare_results.Comparison(rtol=1.0)).beyond != []  # a count vs a float


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("cc") is None and not os.environ.get("CC"), reason="no C compiler")
def test_c_kernel_agrees_with_simulate_batch_and_times_the_four_loops():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    cmd = [sys.executable, str(ROOT / "benchmarks" / "c_kernel.py"), "--batch", "8", "--steps", "60",
           "--repeats", "1", "--check-batch", "4", "--json"]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    assert res["check_ok"] and max(res["check"].values()) < 1e-4  # final state and every metric
    assert res["check"]["J_comfort"] < 1e-4 and res["check"]["diverged"] == 0.0
    t = res["cpu_ns_per_cell_update"]
    assert set(t) == {"C kernel, all metrics", "C kernel, no metrics", "XLA default call", "XLA metric-free call"}
    assert all(v > 0 for v in t.values())
    assert res["default_over_metric_free"] > 0 and res["metric_free_over_c"] > 0
