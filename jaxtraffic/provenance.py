"""Where a result came from: code commit (and whether the tree was dirty), package versions, machine.

``provenance()`` is written into every run's summary.json and the evaluation's metrics.json and
REPORT.md, so that a number can be traced to the code and environment that produced it. It imports
nothing from the rest of the package.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

PACKAGES = ("jax", "jaxlib", "flax", "optax", "chex", "numpy", "matplotlib")
_REPO = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(_REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def code_version() -> dict[str, Any]:
    """{"commit": full hash or None (not a git checkout), "dirty": tracked files modified?}."""
    commit = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance() -> dict[str, Any]:
    """Code version, package versions, Python, machine (CPU model, cores, JAX backend and devices), the
    persistent compilation cache directory in use (None: none; ``jaxtraffic.compile_cache``), time."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    import jax

    return {
        **code_version(), "versions": versions, "python": platform.python_version(),
        "machine": {"cpu": _cpu_model(), "cores": os.cpu_count(), "platform": platform.platform(),
                    "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()]},
        "compilation_cache": jax.config.jax_compilation_cache_dir,
        "utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def describe(p: dict[str, Any]) -> str:
    """One line for a report: commit (dirty?), jax/flax/optax versions, CPU and cores."""
    commit = (p.get("commit") or "unknown")[:12] + (" (dirty tree)" if p.get("dirty") else "")
    v = p.get("versions", {})
    return (f"code {commit}; jax {v.get('jax')}, jaxlib {v.get('jaxlib')}, flax {v.get('flax')}, "
            f"optax {v.get('optax')}; "
            f"{p.get('machine', {}).get('cpu')}, {p.get('machine', {}).get('cores')} cores, "
            f"{p.get('machine', {}).get('backend')} backend; {p.get('utc')}")
