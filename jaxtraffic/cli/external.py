"""``evaluate.py --controller NAME=SOURCE:FUNCTION[:ARGUMENT]``: controllers of the user's own, judged on every
experiment wherever PPO is (a policy trained elsewhere, through ``jaxtraffic.ecosystem.policy_as_controller``;
a hand-written law; ...).

SOURCE is a Python file (``examples/sb3_ppo.py``) or an importable module (``mypackage.controllers``);
``FUNCTION(ARGUMENT)`` (or ``FUNCTION()`` without one) returns a ``Controller``, or a pair (``Controller``,
``ControllerGrid``) naming the grid it acts on (default: the baselines' grid, ``control.adapter.baseline_grid``).

Everything of the user's is checked before any work (``load``, then ``check_grids``): a file that does not import
(a syntax error, a failing import, ``sys.exit`` at import), a missing function, a function that fails or returns no
controller, and a controller that cannot act for one step on each plant (a policy built for another grid than
the plant's, unless its ``ControllerGrid`` says so) are refused in one line naming the controller
(``ControllerFailed``, a ``ValueError``: exit status 2). A controller's own exception during the run is said the same
way (``guarded``: while it is traced; ``blamed``: a host callback's failure while it runs).
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import logging
import re
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, TypedDict

import jax

from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.control.base import Controller
from jaxtraffic.ecosystem.normalization import applying, load_obs_normalization, normalization_evidence
from jaxtraffic.paper import laws
from jaxtraffic.paper.numerics import deploy
from jaxtraffic.paper.scenarios import EvalConfig
from jaxtraffic.sim import initial_state, paper_initial_condition

SPEC = re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_.-]*)=(?P<source>[^:]+):(?P<function>[A-Za-z_]\w*)(?::(?P<arg>.*))?$")


class ControllerSpec(TypedDict):
    """One ``--controller NAME=SOURCE:FUNCTION[:ARGUMENT]`` value (``arg``: None without an ARGUMENT)."""

    name: str
    source: str
    function: str
    arg: str | None


def parse(specs: Sequence[str]) -> list[ControllerSpec]:
    """Each ``--controller`` value as {name, source, function, arg}; ``ValueError`` for a malformed one, a
    name taken by a registered law (``paper.laws``) or given twice."""
    out: list[ControllerSpec] = []
    seen: set[str] = set()
    for spec in specs:
        m = SPEC.match(spec)
        if m is None:
            raise ValueError(f"--controller {spec!r}: expected NAME=SOURCE:FUNCTION[:ARGUMENT], e.g. "
                             "sb3=examples/sb3_ppo.py:controller:runs/sb3_ppo.zip")
        if m["name"] in laws.LAWS or m["name"] in seen:
            raise ValueError(f"--controller {spec!r}: the name {m['name']!r} is "
                             + ("given twice" if m["name"] in seen else "a registered law's (paper.laws)"))
        seen.add(m["name"])
        out.append(ControllerSpec(name=m["name"], source=m["source"], function=m["function"], arg=m["arg"]))
    return out


class ControllerFailed(ValueError):
    """A ``--controller``'s own code failed (importing its source, making it, acting): one line naming it;
    ``cause``: what failed, in one line."""

    def __init__(self, message: str, cause: str = ""):
        super().__init__(message)
        self.cause = cause or message


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def why(err: BaseException, files: Sequence[str] = ()) -> str:
    """``err`` in one line: its type and message (a host callback's failure: the user's exception, the last line of
    the message), a ``sys.exit`` named as such, and the last place in ``files`` (the user's sources) it passed."""
    if isinstance(err, ControllerFailed):
        return err.cause
    if isinstance(err, SystemExit):
        return f"it called sys.exit({err.code!r})"
    if isinstance(err, SyntaxError):
        return f"SyntaxError: {err.msg} ({err.filename}, line {err.lineno})"
    text = str(err)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    said = lines[-1] if "callback" in text.lower() and lines else f"{type(err).__name__}: {_one_line(text)}"
    where = [f"{f.filename}, line {f.lineno}" for f in traceback.extract_tb(err.__traceback__)
             if f.filename in files]
    where += [m.group(1) + ", line " + m.group(2) for m in re.finditer(r'File "([^"]+)", line (\d+)', text)
              if m.group(1) in files]
    return said[:400] + (f" (at {where[-1]})" if where else "")


def _module(name: str, source: str) -> ModuleType:
    """The module of ``source`` (a .py file or an importable module); ``ControllerFailed`` if it does not import."""
    try:
        if source.endswith(".py"):
            path = Path(source)
            if not path.is_file():
                raise ControllerFailed(f"--controller {name}: no file {source}")
            spec = importlib.util.spec_from_file_location(f"jaxtraffic_user_{path.stem}", path.resolve())
            if spec is None or spec.loader is None:  # (not for a .py file: its loader is the source loader)
                raise ControllerFailed(f"--controller {name}: cannot import {source}")
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module
        return importlib.import_module(source)
    except ControllerFailed:
        raise
    except (Exception, SystemExit) as err:  # the user's code: anything, sys.exit included
        cause = why(err, [str(Path(source).resolve())])
        raise ControllerFailed(f"--controller {name}: importing {source} failed: {cause}", cause) from None


def sources(specs: Sequence[str]) -> dict[str, str]:
    """name -> the file of its SOURCE (absolute; a module's once imported), to find it in a traceback."""
    out = {}
    for s in parse(specs):
        if s["source"].endswith(".py"):
            out[s["name"]] = str(Path(s["source"]).resolve())
        else:
            with contextlib.suppress(Exception):
                spec = importlib.util.find_spec(s["source"])
                if spec is not None and spec.origin:
                    out[s["name"]] = spec.origin
    return out


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
    -> the VecNormalize statistics its policy is fed through (``ecosystem.normalization.applying``). Every
    controller is ``guarded``; ``ControllerFailed`` (one line naming it) for a source that does not import, a
    missing function, one that fails (``sys.exit`` included) or returns no controller."""
    controllers: dict[str, Controller] = {}
    grids: dict[str, ControllerGrid] = {}
    normalization = normalization or {}
    for s in parse(specs):
        name, call = s["name"], f"{s['function']}({s['arg'] or ''})"
        function = getattr(_module(name, s["source"]), s["function"], None)
        if not callable(function):
            raise ControllerFailed(f"--controller {name}: {s['source']} has no function {s['function']}")
        stats = load_obs_normalization(normalization[name]) if name in normalization else None
        try:
            with applying(stats):
                made: Any = function(s["arg"]) if s["arg"] is not None else function()
        except (Exception, SystemExit) as err:  # the user's code: anything, sys.exit included
            cause = why(err, list(sources(specs).values()))
            raise ControllerFailed(f"--controller {name}: {call} failed: {cause}", cause) from None
        controller, grid = made if isinstance(made, tuple) and len(made) == 2 else (made, None)
        if not isinstance(controller, Controller) or not (grid is None or isinstance(grid, ControllerGrid)):
            raise ControllerFailed(f"--controller {name}: {call} returned {type(made).__name__}, not a "
                                   "Controller or a (Controller, ControllerGrid) pair")
        controllers[name] = guarded(name, controller)
        if grid is not None:
            grids[name] = grid
    return controllers, grids


def guarded(name: str, controller: Controller) -> Controller:
    """``controller`` whose ``init_fn`` / ``act_fn`` raise ``ControllerFailed`` naming it for any exception of
    theirs (while they are traced; ``sys.exit`` included); its numbers are unchanged."""

    def wrap(fn: Callable) -> Callable:
        def call(*args: Any) -> Any:
            try:
                return fn(*args)
            except ControllerFailed:
                raise
            except (Exception, SystemExit) as err:  # the user's code: anything, sys.exit included
                raise ControllerFailed(f"--controller {name} failed: {why(err)}", why(err)) from None
        return call

    return controller.replace(act_fn=wrap(controller.act_fn), init_fn=wrap(controller.init_fn))


def check_grids(own: Mapping[str, Controller], grids: Mapping[str, ControllerGrid],
                configs: Mapping[str, EvalConfig]) -> None:
    """Each of ``own`` (on its grid of ``grids``, else the baselines') acting for one step on each plant of
    ``configs`` (compiled and run: a host policy is called once), before any work; ``ControllerFailed`` naming
    the first that cannot, e.g. a policy built for another grid than the plant's."""
    hint = ("if it was built for another grid, say so: return (controller, ControllerGrid(n_points=N, dt=DT)) "
            "from its function (docs/tutorials/own-policy.md)")
    for plant, config in configs.items():
        nom = config.nominal()
        rho0, v0 = paper_initial_condition(nom)
        batch = jax.tree.map(lambda a: a[None], initial_state(nom, rho0, v0).observation(nom))  # a batch of 1
        for name, ctrl in own.items():
            grid = grids.get(name)
            on = f"the {plant} plant ({config.describe()})"
            try:
                acting = deploy({name: ctrl}, dict(grids), config)[name]
            except ValueError as err:
                raise ControllerFailed(f"--controller {name}: its grid ({grid.n_points if grid else '?'} points, "
                                       f"dt = {grid.dt if grid else '?'} s) does not fit {on}: {err}") from None
            try:
                h = jax.jit(jax.vmap(_one_step(nom), in_axes=(None, 0)))(acting, batch)  # as in the rollouts
                jax.block_until_ready(h)
            except (Exception, SystemExit) as err:
                cause = why(err, [])
                grid_like = any(w in cause.lower() for w in ("shape", "n_points", "size", "segments"))
                raise ControllerFailed(f"--controller {name} cannot act on {on}: {cause}"
                                       + (f"; {hint}" if grid_like else ""), cause) from None


def _one_step(nom: Any) -> Callable:
    """(controller, observation) -> the time gap it sends first on the plant of ``nom`` (s)."""
    return lambda c, o: c.act(c.init(o, nom), o, nom, jax.random.PRNGKey(0))[0]


@contextlib.contextmanager
def blamed(specs: Sequence[str]) -> Iterator[None]:
    """Say a failure of a ``--controller``'s code during the run as ``ControllerFailed`` naming it: one whose
    traceback or message passes its source file, or a host callback's failure (the baselines have none; with
    several controllers of the user's, all are named). jax's own log of a failed callback is silenced."""
    names = sources(specs)
    log = logging.getLogger("jax._src.callback")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    except ControllerFailed:
        raise
    except Exception as err:
        text = str(err) + "".join(f.filename for f in traceback.extract_tb(err.__traceback__))
        hit = [n for n, f in names.items() if f in text]
        if not hit and "callback" in str(err).lower():
            hit = [s["name"] for s in parse(specs)]
        if not hit:
            raise
        cause = why(err, list(names.values()))
        raise ControllerFailed(f"--controller {' or '.join(hit)} failed during the run: {cause}", cause) from None
    finally:
        log.setLevel(level)
