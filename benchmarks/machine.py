"""Machine description shared by the benchmark scripts (CPU model, load average)."""

from __future__ import annotations

import os
import platform
import subprocess


def cpu_model() -> str:
    """The CPU model name from ``lscpu`` (or platform.processor())."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or "unknown"


def load() -> list[float]:
    """1, 5 and 15 minute load averages."""
    return [round(x, 2) for x in os.getloadavg()]


def _cpuinfo_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def simd_lanes_f32() -> int:
    """float32 lanes of the widest vector unit (AVX-512: 16, AVX2: 8, else 4)."""
    flags = _cpuinfo_flags()
    return 16 if "avx512f" in flags else 8 if "avx2" in flags else 4


def cpu_ghz() -> float:
    """The clock from /proc/cpuinfo ("cpu MHz", a VM's nominal clock), default 2.5 GHz."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("cpu MHz"):
                    return float(line.split(":", 1)[1]) / 1000.0
    except (OSError, ValueError):
        pass
    return 2.5
