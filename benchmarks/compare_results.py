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

``--from-veh-per-m``: the first tree was written before densities were reported in veh/km (metrics.json,
robustness.json, judge.json and the runs' summaries held the density norms, spreads and offsets in veh/m, the
state's unit); its values are converted (``upgrade``: x 1000, the keys and unit strings renamed) before comparing.

Prints, per file, the differences beyond the tolerance (the first few), how many values are within it but
not equal and the largest relative difference; then the totals. Exit status 1 if any difference exceeds it.
"""

from __future__ import annotations

import argparse
import json
import math
import re
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


# the density quantities an older tree held in veh/m (the state's unit): now in veh/km
DENSITY_KEYS = {"final_rho_L2", "final_rho_spatial_std", "final_rho_offset", "late_max_rho_spatial_std", "paper_rho_L2",
                "paper_rho_spatial_std", "rho_bar_veh_per_m", "rho_veh_per_m"}
_AMP = re.compile(r"amp=([0-9.eE+-]+) ")


def upgrade(x: Any, key: str = "", ratio: bool = False) -> Any:
    """An older tree's JSON value with its densities in veh/km (see the module docstring): the values under
    ``DENSITY_KEYS`` x 1000 (``*_veh_per_m`` renamed ``*_veh_per_km``; not below a key naming relative differences
    or ratios, ``ratio``), "veh/m" -> "veh/km" in the unit strings, and the PPO validation labels' amplitude in
    veh/km."""
    if isinstance(x, dict):
        return {k.replace("_veh_per_m", "_veh_per_km"): (
            _units(v) if k == "units" else upgrade(v, k, ratio or "rel" in k or "ratio" in k)) for k, v in x.items()}
    if isinstance(x, list):
        return [upgrade(v, key, ratio) for v in x]
    if isinstance(x, float) and key in DENSITY_KEYS and not ratio:
        return 1000.0 * x
    if isinstance(x, str):
        return _AMP.sub(lambda m: f"amp={1000.0 * float(m.group(1)):g} veh/km ", x)
    return x


def _units(u: Any) -> Any:
    if isinstance(u, dict):
        return {k: _units(v) for k, v in u.items()}
    return re.sub(r"\bveh/m\b(?!²)", "veh/km", u) if isinstance(u, str) else u


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
    parser.add_argument("--from-veh-per-m", action="store_true",
                        help="the first tree holds densities in veh/m (an older version): convert them first")
    args = parser.parse_args(argv)
    rtol, atol = (0.0, 0.0) if args.exact else (args.rtol, args.atol)
    total, rounding, max_rel = 0, 0, 0.0
    for path in sorted(args.a.rglob("*.json")):
        rel = path.relative_to(args.a)
        other = args.b / rel
        if not other.exists():
            print(f"{rel}: only in {args.a}")
            continue
        old = json.loads(path.read_text())
        c = compare(upgrade(old) if args.from_veh_per_m else old, json.loads(other.read_text()),
                    Comparison(rtol=rtol, atol=atol))
        print(f"{rel}: {len(c.beyond)} differences beyond rtol {rtol:g}, atol {atol:g}"
              + (f", e.g. {c.beyond[:3]}" if c.beyond else "")
              + f"; {c.rounding} floats within it, largest relative difference {c.max_rel:.1e}")
        total, rounding, max_rel = total + len(c.beyond), rounding + c.rounding, max(max_rel, c.max_rel)
    print(f"total: {total} differences beyond the tolerance (rtol {rtol:g}, atol {atol:g}; integers, booleans and "
          f"strings exactly); {rounding} floats differ within it; largest relative difference {max_rel:.1e}")
    return 1 if total else 0


if __name__ == "__main__":
    raise SystemExit(main())
