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
from pathlib import Path
from types import ModuleType
from typing import Any

from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.control.base import Controller
from jaxtraffic.paper.scenarios import BASELINES, EXTRA_LEARNED

RESERVED = {*BASELINES, "ppo", *EXTRA_LEARNED}
SPEC = re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_.-]*)=(?P<source>[^:]+):(?P<function>[A-Za-z_]\w*)(?::(?P<arg>.*))?$")


def parse(specs: list[str]) -> list[dict[str, str | None]]:
    """Each ``--controller`` value as {name, source, function, arg}; ``ValueError`` for a malformed one, a
    name taken by a built-in controller or given twice."""
    out, seen = [], set()
    for spec in specs:
        m = SPEC.match(spec)
        if m is None:
            raise ValueError(f"--controller {spec!r}: expected NAME=SOURCE:FUNCTION[:ARGUMENT], e.g. "
                             "sb3=examples/sb3_ppo.py:controller:runs/sb3_ppo.zip")
        if m["name"] in RESERVED or m["name"] in seen:
            raise ValueError(f"--controller {spec!r}: the name {m['name']!r} is "
                             + ("given twice" if m["name"] in seen else "a built-in controller's"))
        seen.add(m["name"])
        out.append(m.groupdict())
    return out


def _module(source: str) -> ModuleType:
    if source.endswith(".py"):
        path = Path(source)
        if not path.is_file():
            raise ValueError(f"--controller: no file {source}")
        spec = importlib.util.spec_from_file_location(f"jaxtraffic_user_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return importlib.import_module(source)


def load(specs: list[str]) -> tuple[dict[str, Controller], dict[str, ControllerGrid]]:
    """(name -> controller, name -> its grid when given) of the ``--controller`` values."""
    controllers, grids = {}, {}
    for s in parse(specs):
        function = getattr(_module(s["source"]), s["function"], None)
        if not callable(function):
            raise ValueError(f"--controller {s['name']}: {s['source']} has no function {s['function']}")
        made: Any = function(s["arg"]) if s["arg"] is not None else function()
        controller, grid = made if isinstance(made, tuple) else (made, None)
        if not isinstance(controller, Controller) or not (grid is None or isinstance(grid, ControllerGrid)):
            raise ValueError(f"--controller {s['name']}: {s['function']} returned {type(made).__name__}, not a "
                             "Controller or a (Controller, ControllerGrid) pair")
        controllers[s["name"]] = controller
        if grid is not None:
            grids[s["name"]] = grid
    return controllers, grids
