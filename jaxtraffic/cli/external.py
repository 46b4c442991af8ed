"""``evaluate.py --controller NAME=SOURCE:FUNCTION[:ARGUMENT]``: controllers of the user's own, judged on every
experiment wherever PPO is (a policy trained elsewhere, through ``jaxtraffic.ecosystem.policy_as_controller``;
a hand-written law; ...).

SOURCE is a Python file (``examples/sb3_ppo.py``) or an importable module (``mypackage.controllers``);
``FUNCTION(ARGUMENT)`` (or ``FUNCTION()`` without one) returns a ``Controller``, or a pair (``Controller``,
``ControllerGrid``) naming the grid it acts on (default: the baselines' grid, ``control.adapter.baseline_grid``).
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, TypedDict

from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.control.base import Controller
from jaxtraffic.ecosystem.normalization import applying, load_obs_normalization, normalization_evidence
from jaxtraffic.paper.scenarios import BASELINES, EXTRA_LEARNED

RESERVED = {*BASELINES, "ppo", *EXTRA_LEARNED}
SPEC = re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_.-]*)=(?P<source>[^:]+):(?P<function>[A-Za-z_]\w*)(?::(?P<arg>.*))?$")


class ControllerSpec(TypedDict):
    """One ``--controller NAME=SOURCE:FUNCTION[:ARGUMENT]`` value (``arg``: None without an ARGUMENT)."""

    name: str
    source: str
    function: str
    arg: str | None


def parse(specs: Sequence[str]) -> list[ControllerSpec]:
    """Each ``--controller`` value as {name, source, function, arg}; ``ValueError`` for a malformed one, a
    name taken by a built-in controller or given twice."""
    out: list[ControllerSpec] = []
    seen: set[str] = set()
    for spec in specs:
        m = SPEC.match(spec)
        if m is None:
            raise ValueError(f"--controller {spec!r}: expected NAME=SOURCE:FUNCTION[:ARGUMENT], e.g. "
                             "sb3=examples/sb3_ppo.py:controller:runs/sb3_ppo.zip")
        if m["name"] in RESERVED or m["name"] in seen:
            raise ValueError(f"--controller {spec!r}: the name {m['name']!r} is "
                             + ("given twice" if m["name"] in seen else "a built-in controller's"))
        seen.add(m["name"])
        out.append(ControllerSpec(name=m["name"], source=m["source"], function=m["function"], arg=m["arg"]))
    return out


def _module(source: str) -> ModuleType:
    if source.endswith(".py"):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"--controller: no file {source}")
        spec = importlib.util.spec_from_file_location(f"jaxtraffic_user_{path.stem}", path)
        if spec is None or spec.loader is None:  # (not for a .py file: its loader is the source loader)
            raise ValueError(f"--controller: cannot import {source}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return importlib.import_module(source)


def parse_normalization(specs: Sequence[str], controllers: Sequence[str]) -> dict[str, Path]:
    """``--controller-normalization NAME=FILE`` values as name -> file; ``ValueError`` for a malformed one, or
    one naming no ``--controller``."""
    out: dict[str, Path] = {}
    for spec in specs:
        name, sep, file = spec.partition("=")
        if not sep or not file or name not in controllers or name in out:
            raise ValueError(f"--controller-normalization {spec!r}: expected NAME=FILE, NAME a --controller given "
                             "once (the file of jaxtraffic.ecosystem.normalization.export_obs_normalization)")
        out[name] = Path(file)
    return out


def unnormalised(specs: Sequence[str], normalization: dict[str, Path]) -> str | None:
    """Why a ``--controller`` must be refused: its ARGUMENT is a model file with a ``vecnormalize*.pkl`` beside it
    (trained under SB3's VecNormalize) and no ``--controller-normalization`` for it; None when none is."""
    for s in parse(specs):
        found = normalization_evidence(s["arg"]) if s["arg"] and Path(s["arg"]).is_file() else None
        if found is not None and s["name"] not in normalization:
            return (f"--controller {s['name']}: {found} says it was trained under VecNormalize; export its statistics "
                    "(jaxtraffic.ecosystem.normalization.export_obs_normalization) and give "
                    f"--controller-normalization {s['name']}=FILE")
    return None


def load(specs: Sequence[str], normalization: dict[str, Path] | None = None
         ) -> tuple[dict[str, Controller], dict[str, ControllerGrid]]:
    """(name -> controller, name -> its grid when given) of the ``--controller`` values; ``normalization``: name
    -> the VecNormalize statistics its policy is fed through (``ecosystem.normalization.applying``)."""
    controllers: dict[str, Controller] = {}
    grids: dict[str, ControllerGrid] = {}
    normalization = normalization or {}
    for s in parse(specs):
        function = getattr(_module(s["source"]), s["function"], None)
        if not callable(function):
            raise ValueError(f"--controller {s['name']}: {s['source']} has no function {s['function']}")
        stats = load_obs_normalization(normalization[s["name"]]) if s["name"] in normalization else None
        with applying(stats):
            made: Any = function(s["arg"]) if s["arg"] is not None else function()
        controller, grid = made if isinstance(made, tuple) else (made, None)
        if not isinstance(controller, Controller) or not (grid is None or isinstance(grid, ControllerGrid)):
            raise ValueError(f"--controller {s['name']}: {s['function']} returned {type(made).__name__}, not a "
                             "Controller or a (Controller, ControllerGrid) pair")
        controllers[s["name"]] = controller
        if grid is not None:
            grids[s["name"]] = grid
    return controllers, grids
