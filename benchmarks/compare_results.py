"""Compare every number of two results trees' JSON files (what ``evaluate.py`` writes): metrics, robustness,
claims, plants, the runs' summaries and configs. Wall times, provenance and other clock readings are skipped.

    python benchmarks/compare_results.py docs/results results                 # rounding-level tolerance
    python benchmarks/compare_results.py docs/results results --exact         # bit for bit
    python benchmarks/compare_results.py docs/results gpu_results --rtol 1e-3 # another backend

The tolerances (issue 48: results regenerated after a change that moves numbers at float rounding, or computed
on another backend, are compared with tolerances; counts never):

- **floats** agree when |a - b| <= atol + rtol max(|a|, |b|) (NaN equals NaN, an infinity only itself).
  ``--rtol`` default 1e-5: the simulator runs in float32 (eps 1.2e-7) and a rollout's sums and final
  fields gather a few ulp per step over thousands of steps; two XLA programs of the same loop that fuse
  differently (a metric selection, reduce-first sums) were measured within a few 1e-6 relative. Across
  backends (CPU / GPU: other reduction orders, fused multiply-adds) give ``--rtol 1e-3`` or so.
  ``--atol`` default 0: a value near zero (an L2 norm of a converged state) then needs the relative test too;
  give e.g. ``--atol 1e-9`` where such values differ. A trained policy (PPO, gradient) amplifies any
  rounding difference into another trajectory: its numbers are not expected to meet either tolerance.
- **integers, booleans and strings** must be equal: the robustness map's counts (stabilised, diverged),
  divergence flags and steps, checkpoint steps, names. A map count that moves is a difference at any
  tolerance.

Prints, per file, the differences beyond the tolerance (the first few), how many values are within it but
not equal and the largest relative difference; then the totals. Exit status 1 if any difference exceeds it.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SKIP = {"provenance", "created", "commit", "date", "time", "version", "host", "machine"}
CLOCK = ("wall", "seconds", "time_s", "runtime")  # keys holding clock readings (differ between runs)
RTOL = 1e-5  # default relative tolerance of floats (dimensionless): float32 rounding over a rollout
ATOL = 0.0  # default absolute tolerance of floats (units of each value)


@dataclass
class Comparison:
    """What ``compare`` found: ``beyond`` (path, a's value, b's value) outside the tolerance; ``rounding``: how
    many floats differ within it; ``max_rel``: the largest relative difference of two unequal finite floats."""

    rtol: float = RTOL
    atol: float = ATOL
    beyond: list[tuple] = field(default_factory=list)
    rounding: int = 0
    max_rel: float = 0.0


def _floats_close(x: float, y: float, c: Comparison) -> bool:
    if x == y or (math.isnan(x) and math.isnan(y)):
        return True
    if not (math.isfinite(x) and math.isfinite(y)):
        return False
    rel = abs(x - y) / max(abs(x), abs(y))
    c.max_rel = max(c.max_rel, rel)
    if abs(x - y) <= c.atol + c.rtol * max(abs(x), abs(y)):
        c.rounding += 1
        return True
    return False


def compare(a: Any, b: Any, c: Comparison, path: str = "") -> Comparison:
    """Walk two JSON values, adding to ``c`` every leaf that differs (floats beyond its tolerance; any other
    leaf, or a float against a non-float, when not equal). Returns ``c``."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key in SKIP or any(k in key for k in CLOCK):
                continue
            if key not in a or key not in b:
                c.beyond.append((f"{path}/{key}", "present" if key in a else "absent",
                                 "present" if key in b else "absent"))
            else:
                compare(a[key], b[key], c, f"{path}/{key}")
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            c.beyond.append((path, f"{len(a)} items", f"{len(b)} items"))
        else:
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                compare(x, y, c, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        if not _floats_close(a, b, c):
            c.beyond.append((path, a, b))
    elif not (a == b and type(a) is type(b)):  # ints (counts), bools, strings, None: exactly
        c.beyond.append((path, a, b))
    return c


def differences(a: Any, b: Any, path: str = "", rtol: float = 0.0, atol: float = 0.0) -> list[tuple]:
    """(path, a's value, b's value) of every leaf that differs beyond the tolerance (default: bit for bit)."""
    return compare(a, b, Comparison(rtol=rtol, atol=atol), path).beyond


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--rtol", type=float, default=RTOL, help=f"relative tolerance of floats (default {RTOL:g})")
    parser.add_argument("--atol", type=float, default=ATOL, help=f"absolute tolerance of floats (default {ATOL:g})")
    parser.add_argument("--exact", action="store_true", help="bit for bit (rtol = atol = 0)")
    args = parser.parse_args(argv)
    rtol, atol = (0.0, 0.0) if args.exact else (args.rtol, args.atol)
    total, rounding, max_rel = 0, 0, 0.0
    for path in sorted(args.a.rglob("*.json")):
        rel = path.relative_to(args.a)
        other = args.b / rel
        if not other.exists():
            print(f"{rel}: only in {args.a}")
            continue
        c = compare(json.loads(path.read_text()), json.loads(other.read_text()), Comparison(rtol=rtol, atol=atol))
        print(f"{rel}: {len(c.beyond)} differences beyond rtol {rtol:g}, atol {atol:g}"
              + (f", e.g. {c.beyond[:3]}" if c.beyond else "")
              + f"; {c.rounding} floats within it, largest relative difference {c.max_rel:.1e}")
        total, rounding, max_rel = total + len(c.beyond), rounding + c.rounding, max(max_rel, c.max_rel)
    print(f"total: {total} differences beyond the tolerance (rtol {rtol:g}, atol {atol:g}; integers, booleans and "
          f"strings exactly); {rounding} floats differ within it; largest relative difference {max_rel:.1e}")
    return 1 if total else 0


if __name__ == "__main__":
    raise SystemExit(main())
