#!/usr/bin/env python
"""Check the dependency floors in pyproject.toml: install exactly the lowest allowed versions of
jax (and jaxlib), flax, optax and chex (numpy and matplotlib as pip resolves them) into a fresh
virtual environment, install jaxtraffic there without dependencies, and run a subset of the tests against them.

    python benchmarks/check_dependency_bounds.py                # the floors of pyproject.toml
    python benchmarks/check_dependency_bounds.py --pin jax==0.5.0 --pin flax==0.10.0
    python benchmarks/check_dependency_bounds.py --venv /tmp/floor --keep   # reuse the environment
    python benchmarks/check_dependency_bounds.py --extras       # and the extras' floors, their tests

Opt-in (not part of .ci/run: it downloads ~150 MB of wheels and takes minutes). The ceilings
(``<`` bounds) are the newest versions the full suite is run with; the results are recorded in
BENCHMARKS.md ("Dependency bounds"). Exit status: pytest's (0 when the subset passes).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHECKED = ("jax", "flax", "optax", "chex")  # pinned to their floors; numpy, matplotlib: resolved by pip
# fast tests that touch every layer: the solver and delay buffer (jax), the environment (flax struct,
# chex), PPO maths and a short training (optax, flax.linen), the policy round trip, batches sharded
# over 1 and 2 devices (jax.shard_map), gradient training (optax.tree, checkpoints)
TESTS = ["tests/test_solver.py", "tests/test_delay.py", "tests/test_env.py", "tests/test_ppo.py",
         "tests/test_gain_policy.py", "tests/test_sharding.py", "tests/test_gradient.py"]


EXTRAS = ("gym", "gymnax", "sb3", "tb")  # --extras: their floors pinned too, their tests run, none may skip
EXTRA_TESTS = ["tests/test_ecosystem_gym.py", "tests/test_ecosystem_gymnax.py", "tests/test_ecosystem_logging.py"]
TORCH = "torch==2.13.0"  # what stable-baselines3 runs on here (the CPU build kept on this kind of machine's disk)


def extra_floors() -> dict[str, str]:
    """{package: lowest allowed version} of every package the ``EXTRAS`` of pyproject.toml ask for."""
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    found = (re.match(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9][^,;\s]*)", d) for e in EXTRAS for d in extras[e])
    return {m.group(1).lower(): m.group(2) for m in found if m}


def dependencies() -> list[str]:
    """The ``[project] dependencies`` of pyproject.toml."""
    text = (REPO / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)\]", text, re.S | re.M).group(1)
    return re.findall(r'"([^"]+)"', re.sub(r"#[^\n]*", "", block))  # comments dropped


def floors() -> dict[str, str]:
    """{package: lowest allowed version} of the checked packages, from pyproject.toml."""
    found = (re.match(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9][^,;\s]*)", d) for d in dependencies())
    return {m.group(1).lower(): m.group(2) for m in found if m and m.group(1).lower() in CHECKED}


def run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    print("+", " ".join(cmd), flush=True)
    return subprocess.run(cmd, check=False, **kw)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--venv", type=Path, default=Path("/tmp/jaxtraffic-floor-venv"))
    ap.add_argument("--pin", action="append", default=[], help="NAME==VERSION overriding a floor (repeatable)")
    ap.add_argument("--keep", action="store_true", help="reuse --venv if it exists")
    ap.add_argument("--tests", nargs="*", default=TESTS)
    ap.add_argument("--extras", action="store_true",
                    help=f"also pin the floors of the extras {', '.join(EXTRAS)} (and {TORCH}) and run their tests")
    args = ap.parse_args(argv)
    pins = {k: f"{k}=={v}" for k, v in floors().items()}
    tests, env = list(args.tests), None
    if args.extras:
        pins.update({k: f"{k}=={v}" for k, v in extra_floors().items()})
        pins["torch"] = TORCH
        tests += [t for t in EXTRA_TESTS if t not in tests]
        env = {**__import__("os").environ, "JAXTRAFFIC_REQUIRE_EXTRAS": "1"}
    for p in args.pin:
        pins[p.split("==")[0].lower()] = p
    if "jax" in pins:  # jaxlib must match jax at these versions
        pins["jaxlib"] = "jaxlib==" + pins["jax"].split("==")[1]
    py = args.venv / "bin" / "python"
    t0 = time.perf_counter()
    if not (args.keep and py.exists()):
        if run([sys.executable, "-m", "venv", "--clear", str(args.venv)]).returncode:
            return 1
    others = [d for d in dependencies() if re.match(r"[A-Za-z0-9_.-]+", d).group(0).lower() not in pins]
    if run([str(py), "-m", "pip", "install", "-q", *pins.values(), *others, "pytest", "pytest-xdist"]).returncode:
        print("the pinned versions cannot be installed together", file=sys.stderr)
        return 1
    if run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(REPO)]).returncode:
        return 1
    names = ("jaxlib",) + CHECKED + ("numpy", "scipy", "matplotlib")
    if args.extras:
        names += tuple(k for k in pins if k not in names)
    got = run([str(py), "-c", "import importlib.metadata as m; print(' '.join(f'{p}=={m.version(p)}' for p in "
               f"{names!r}))"], capture_output=True, text=True).stdout.strip()
    print("installed:", got, flush=True)
    # run from a temporary directory against the installed package (not the work tree)
    rc = run([str(py), "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(REPO),
              *[str(REPO / t) for t in tests]], cwd="/tmp", env=env).returncode
    print(f"RESULT pins={' '.join(pins.values())} installed={got} pytest_exit={rc} "
          f"wall={time.perf_counter() - t0:.0f}s", flush=True)
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
