"""Compare every number of two results trees' JSON files (what ``evaluate.py`` writes): metrics, robustness,
claims, plants, the runs' summaries and configs. Wall times, provenance and other clock readings are skipped.

    python benchmarks/compare_results.py docs/results results

prints, per file, how many values differ (and the first few), then the total; exit status 1 if any differ.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

SKIP = {"provenance", "created", "commit", "date", "time", "version", "host", "machine"}
CLOCK = ("wall", "seconds", "time_s", "runtime")  # keys holding clock readings (differ between runs)


def differences(a: Any, b: Any, path: str = "") -> list[tuple]:
    """(path, a's value, b's value) of every leaf that differs (NaN equals NaN)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if key in SKIP or any(c in key for c in CLOCK):
                continue
            if key not in a or key not in b:
                out.append((f"{path}/{key}", "present" if key in a else "absent", "present" if key in b else "absent"))
            else:
                out += differences(a[key], b[key], f"{path}/{key}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [(path, f"{len(a)} items", f"{len(b)} items")]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{path}[{i}]")]
    same = a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))
    return [] if same else [(path, a, b)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    args = parser.parse_args(argv)
    total = 0
    for path in sorted(args.a.rglob("*.json")):
        rel = path.relative_to(args.a)
        other = args.b / rel
        if not other.exists():
            print(f"{rel}: only in {args.a}")
            continue
        diff = differences(json.loads(path.read_text()), json.loads(other.read_text()))
        print(f"{rel}: {len(diff)} differences" + (f", e.g. {diff[:3]}" if diff else ""))
        total += len(diff)
    print(f"total: {total} differences")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
