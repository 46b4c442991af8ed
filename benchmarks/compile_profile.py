"""Where a job's compilation time goes (issue 48 item 3): reads the log of a run made with ``JAX_LOG_COMPILES=1``
and prints, per program name, how many times it was compiled and the time spent in tracing, lowering and XLA
compilation (s), the largest first, with the totals.

    JAX_LOG_COMPILES=1 python evaluate.py --out results 2> compile.log
    python benchmarks/compile_profile.py compile.log [--top 25]

A name compiled many times is a candidate for one program with traced coefficients, a bucketed batch size or a
traced horizon. A persistent-cache hit logs no "XLA compilation" line (its tracing and lowering still show).
"""

from __future__ import annotations

import argparse
import re
from collections import defaultdict
from pathlib import Path

STAGES = {"tracing": re.compile(r"Finished tracing (\S+) for jit in ([0-9.e+-]+) sec"),
          "lowering": re.compile(r"Finished jaxpr to MLIR module conversion jit\((.*)\) in ([0-9.e+-]+) sec"),
          "xla": re.compile(r"Finished XLA compilation of jit\((.*)\) in ([0-9.e+-]+) sec")}


def profile(lines: list[str]) -> dict[str, dict[str, float]]:
    """Program name -> {"count": XLA compilations, "tracing"/"lowering"/"xla": seconds}."""
    out: dict[str, dict[str, float]] = defaultdict(lambda: {"count": 0, "tracing": 0.0, "lowering": 0.0, "xla": 0.0})
    for line in lines:
        for stage, pat in STAGES.items():
            m = pat.search(line)
            if m:
                out[m.group(1)][stage] += float(m.group(2))
                out[m.group(1)]["count"] += stage == "xla"
    return dict(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", type=Path)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    prof = profile(args.log.read_text(errors="replace").splitlines())
    rows = sorted(prof.items(), key=lambda kv: -(kv[1]["xla"] + kv[1]["lowering"] + kv[1]["tracing"]))
    print("| program | XLA compilations | tracing (s) | lowering (s) | XLA (s) |\n|---|---:|---:|---:|---:|")
    for name, p in rows[:args.top]:
        print(f"| `{name[:60]}` | {int(p['count'])} | {p['tracing']:.1f} | {p['lowering']:.1f} | {p['xla']:.1f} |")
    tot = {k: sum(p[k] for p in prof.values()) for k in ("count", "tracing", "lowering", "xla")}
    print(f"| **all {len(prof)} programs** | {int(tot['count'])} | {tot['tracing']:.1f} | {tot['lowering']:.1f} | "
          f"{tot['xla']:.1f} |")


if __name__ == "__main__":
    main()
