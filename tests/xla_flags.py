"""The XLA flags of the test processes (one place; no jax import, so conftest can apply them first).

Compilation dominates these tiny-grid tests, so the test process and its training subprocesses compile
with cheaper settings, each added only when XLA_FLAGS does not already choose it:

- ``--xla_backend_optimization_level=0``: LLVM's optimisation off (-23 % CPU on test_baselines +
  test_delay, measured);
- ``--xla_cpu_use_fusion_emitters=false``: XLA:CPU's older loop emitters instead of its MLIR fusion
  emitters, about 3x less backend compile time on a closed-loop rollout (default tier 272 -> 152 s
  wall, 410 -> 217 s CPU; BENCHMARKS.md "Test suite time"). Not for users: at the default
  optimisation level these kernels run ~2.5x slower than the fusion emitters'.

Fusion can differ between two programs by an ulp under these flags, so tests compare different
programs to a few ulps, and compare bit for bit only a program with itself (determinism, resume).
"""

from __future__ import annotations

import os

TEST_FLAGS = ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false")


def with_test_flags(flags: str = "", *extra: str) -> str:
    """``flags`` plus each of ``TEST_FLAGS`` whose name it does not set, plus ``extra``."""
    added = [f for f in TEST_FLAGS if f.split("=")[0] not in flags]
    return " ".join(filter(None, [flags, *added, *extra]))


def apply() -> None:
    """Set the test flags in this process's XLA_FLAGS (before jax initialises its backend)."""
    os.environ["XLA_FLAGS"] = with_test_flags(os.environ.get("XLA_FLAGS", ""))
