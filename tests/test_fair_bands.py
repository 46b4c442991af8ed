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


def test_rows_judged_again_and_merged_equal_a_run_of_every_row(tmp_path):
    """``fair_benchmark.py --only ... --merge-into``: a row judged on its own and merged into an earlier run's JSON
    gives the same measures, table and checks as one run of every row (each row's measures depend only on its law
    and the scenarios); a run on other scenarios is refused."""
    import pytest

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import fair_benchmark

    import jaxtraffic as jt
    from jaxtraffic.compare import LawSpec
    from jaxtraffic.paper import fair

    base = jt.TrafficParams(n_points=21)
    ref = LawSpec("backstepping", "backstepping", jt.backstepping, "delay")  # the tables' reference row
    a, b = LawSpec("a", "law A", lambda: jt.lyapunov(0.5)), LawSpec("b", "law B", lambda: jt.lyapunov(1.5))
    b_before = LawSpec("b", "law B", lambda: jt.lyapunov(0.1))  # the row as it was before it is judged again
    quiet = dict(n=6, horizon_s=20.0, log=lambda _: None)
    fair.run([ref, a, b], "tiny", base, tmp_path / "both", **quiet)
    fair.run([ref, a, b_before], "tiny", base, tmp_path / "old", **quiet)
    assert fair_benchmark.only([ref, a, b], ["b"]) == [ref, b]  # --only b judges the reference row too
    new_b = fair.run(fair_benchmark.only([ref, a, b], ["b"]), "tiny", base, None, **quiet)
    path = tmp_path / "old" / "tiny.json"
    old_b = read_json(path)["per_scenario"]["b"]
    write_json(path, fair_benchmark.merge(read_json(path), new_b))
    fair.resummarise(path)
    fair.resummarise(tmp_path / "both" / "tiny.json")  # both summarised from the measures as written (7 digits)
    merged, whole = read_json(path), read_json(tmp_path / "both" / "tiny.json")
    assert merged["per_scenario"] == whole["per_scenario"] and merged["laws"] == whole["laws"]
    assert merged["summary"] == whole["summary"] and merged["checks"] == whole["checks"]
    assert merged["markdown"] == whole["markdown"] and merged["merged"][0]["rows"] == ["backstepping", "b"]
    assert old_b != merged["per_scenario"]["b"]  # the row judged again did replace the earlier one
    with pytest.raises(ValueError, match="backstepping"):  # refused before it simulates, not after
        fair.run([a, b], "tiny", base, None, **quiet)
    other = fair.run([ref, b], "tiny", base, None, seed=1, **quiet)
    with pytest.raises(ValueError, match="scenarios"):
        fair_benchmark.merge(read_json(path), other)
