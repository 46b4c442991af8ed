"""benchmarks/fair_benchmark.py: where each law diverges, by band of the plants' delay and ACC share (an oracle on a
hand-made result), kept when the per-scenario measures are stripped, and replaced, not repeated, when written again."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from jaxtraffic.io.files import read_json, write_json

ROOT = Path(__file__).resolve().parents[1]


def _result() -> dict:
    # 6 scenarios: delays in the bands 0-2, 2-4, 4-6, 6-8 s (8 s: the last band), ACC shares at both ends
    delay, alpha = [0.5, 1.9, 3.0, 5.0, 7.5, 8.0], [0.05, 0.6, 0.1, 0.3, 0.5, 0.6]
    return {"laws": {"a": "law A", "b": "law B"}, "markdown": ["| table |"],
            "scenarios": {"delay": delay, "alpha": alpha},
            "per_scenario": {"a": {"diverged": [False] * 6, "mean_rho_L2": [1.0] * 6},
                             "b": {"diverged": [True, False, False, True, True, True], "mean_rho_L2": [1.0] * 6}}}


def test_divergence_bands_against_a_hand_count_and_kept_by_strip(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import fair_benchmark

    path = tmp_path / "paper.json"
    write_json(path, _result())
    fair_benchmark.add_divergence_bands(path)
    fair_benchmark.add_divergence_bands(path)  # written again: one section
    by = read_json(path)["diverged_by_plant"]
    assert by["n"] == {"delay": [2, 1, 1, 2], "alpha": [2, 1, 0, 3]}
    assert by["bands"]["alpha"][0] == [0.05, 0.1875] and by["bands"]["delay"][-1] == [6.0, 8.0]
    assert by["rates"]["a"] == {"delay": [0.0] * 4, "alpha": [0.0, 0.0, None, 0.0]}
    assert by["rates"]["b"] == {"delay": [0.5, 0.0, 1.0, 1.0], "alpha": [0.5, 1.0, None, 2 / 3]}
    md = (tmp_path / "paper.md").read_text()
    assert md.count("Where each law diverges") == 1
    assert "| law B | 50 % | 0 % | 100 % | 100 % | 50 % | 100 % | - | 67 % |" in md
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "fair_benchmark.py"), "--strip", str(path)],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    stripped = read_json(path)
    assert isinstance(stripped["per_scenario"], str) and stripped["diverged_by_plant"] == by
    assert "markdown" not in stripped and stripped["scenarios"] == _result()["scenarios"]
