"""Where a result came from: jaxtraffic's version, the code commit (and whether the tree was dirty),
package versions, machine.

``provenance()`` is written into every run's summary.json and the evaluation's metrics.json and
REPORT.md, so that a number can be traced to the code and environment that produced it. The commit
is recorded only when the package runs from a git checkout of jaxtraffic itself (an editable
install or the repository); installed from a wheel, even inside a git repository of the user's,
the version says which code ran. It imports nothing from the rest of the package but its version.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from jaxtraffic._version import __version__

PACKAGES = ("jax", "jaxlib", "flax", "optax", "chex", "numpy", "matplotlib")
_REPO = Path(__file__).resolve().parents[2]  # (jaxtraffic/io/provenance.py: the repository is two levels up)


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(_REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _own_checkout() -> bool:
    """Is the package's parent directory the top of a git checkout of jaxtraffic (not merely inside some
    repository, as a site-packages directory of a virtual environment in a user's project is)?"""
    top = _git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != _REPO:
        return False
    try:
        return 'name = "jaxtraffic"' in (_REPO / "pyproject.toml").read_text()
    except OSError:
        return False


def code_version() -> dict[str, Any]:
    """{"version": jaxtraffic's version, "commit": full hash or None (not a checkout of jaxtraffic),
    "dirty": tracked files modified?}."""
    commit = _git("rev-parse", "HEAD") if _own_checkout() else None
    status = _git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"version": __version__, "commit": commit, "dirty": None if status is None else bool(status)}


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
    persistent compilation cache directory in use (None: none; ``jaxtraffic.platform.compile_cache``), time."""
    versions: dict[str, str | None] = {}
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
        "compilation_cache": jax.config.jax_compilation_cache_dir,  # type: ignore[attr-defined]  # (flags: no stub)
        "utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }


def describe(p: dict[str, Any]) -> str:
    """One line for a report: jaxtraffic version and commit (dirty?), jax/flax/optax versions, CPU and cores."""
    commit = (p.get("commit") or "unknown")[:12] + (" (dirty tree)" if p.get("dirty") else "")
    v = p.get("versions", {})
    return (f"jaxtraffic {p.get('version', 'unknown')}, code {commit}; "
            f"jax {v.get('jax')}, jaxlib {v.get('jaxlib')}, flax {v.get('flax')}, "
            f"optax {v.get('optax')}; "
            f"{p.get('machine', {}).get('cpu')}, {p.get('machine', {}).get('cores')} cores, "
            f"{p.get('machine', {}).get('backend')} backend; {p.get('utc')}")
