"""Gymnasium and gymnax registration of the gain environment, run at ``import jaxtraffic``.

Gymnasium 1.x has no plugin (entry-point) registration, so ``gymnasium.make("jaxtraffic/Gain-v0")``
finds the id only once a module has called ``gymnasium.register``. ``import jaxtraffic`` does it
when gymnasium is installed (``find_spec``: nothing is imported when it is not), with string entry
points, so ``jaxtraffic.ecosystem.gym_env`` (and ``learn.env``) are imported only by ``make``.
Cost: the import of gymnasium itself, ~60 ms after jax (docs/model.md section 19.4).
The module-prefixed id ``"jaxtraffic:jaxtraffic/Gain-v0"`` needs no import first: gymnasium imports
``jaxtraffic``, which registers the id.

gymnax (>= 1.0: ``gymnax.register(id, factory)``, no string entry points, no plugins) gets the same id in
either import order: at ``import jaxtraffic`` when gymnax is already imported, else as soon as gymnax is
imported (an import hook on ``sys.meta_path``, ``_GymnaxHook``, installed by ``import jaxtraffic`` when gymnax
is installed: it registers right after gymnax's own module has run, then removes itself). Importing gymnax
costs ~1.2 s (all its environments), so ``import jaxtraffic`` never does it.
``gymnax.make("jaxtraffic/Gain-v0", n_points=21)`` -> ``(GainGymnaxEnv, its default params)``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

ENV_ID = "jaxtraffic/Gain-v0"
GYMNAX_ENTRY = "jaxtraffic.ecosystem.gymnax_env"

__all__ = ["ENV_ID", "register_gymnasium", "register_gymnax"]


def register_gymnasium() -> bool:
    """Register ``ENV_ID`` with gymnasium (entry point ``ecosystem.gym_env.GainEnv``, vector entry
    point ``ecosystem.gym_env.GainVectorEnv``); False when gymnasium is not installed (or fails to
    import). Idempotent."""
    if importlib.util.find_spec("gymnasium") is None:
        return False
    try:
        import gymnasium
    except ImportError:
        return False
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point="jaxtraffic.ecosystem.gym_env:GainEnv",
                           vector_entry_point="jaxtraffic.ecosystem.gym_env:GainVectorEnv")
    return True


def _make_gymnax_env(**config: Any) -> Any:
    """gymnax's factory: ``GainGymnaxEnv(**config)``, its module named by a string as gymnasium's entry points
    are (imported on first use; this bottom layer imports no layer above it)."""
    return importlib.import_module(GYMNAX_ENTRY).GainGymnaxEnv(**config)


class _GymnaxHook(importlib.abc.MetaPathFinder):
    """A one-shot import hook: when ``gymnax`` is first imported, its module runs as usual and then
    ``register_gymnax`` registers ``ENV_ID`` (so ``import jaxtraffic`` before ``import gymnax`` works too)."""

    searching = False  # (find_spec below asks the other finders: this one steps aside)

    def find_spec(self, fullname: str, path: Sequence[str] | None = None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname != "gymnax" or self.searching:
            return None
        self.searching = True
        try:
            spec = importlib.util.find_spec("gymnax")
        finally:
            self.searching = False
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_then_register(module: ModuleType) -> None:
            run(module)
            _unwatch()  # (only once gymnax is imported: a mere find_spec("gymnax") probe leaves the hook)
            try:
                register_gymnax()
            except Exception:  # noqa: BLE001, S110  (never break the user's import of gymnax: make says the id is unknown)
                pass

        spec.loader.exec_module = exec_then_register  # type: ignore[method-assign]  # (this import's loader only)
        return spec


def _unwatch() -> None:
    """Remove every ``_GymnaxHook`` from ``sys.meta_path``."""
    sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _GymnaxHook)]


def register_gymnax(import_gymnax: bool = False) -> bool:
    """Register ``ENV_ID`` with gymnax's registry (``gymnax.make``); False when gymnax is not imported
    (and ``import_gymnax`` is False), not installed, or older than 1.0 (no ``gymnax.register``).
    When gymnax is installed but not imported, a ``_GymnaxHook`` registers it on its import. Idempotent."""
    if "gymnax" not in sys.modules and not import_gymnax:
        if importlib.util.find_spec("gymnax") is not None and not any(
                isinstance(f, _GymnaxHook) for f in sys.meta_path):
            sys.meta_path.insert(0, _GymnaxHook())
        return False
    if "gymnax" not in sys.modules and importlib.util.find_spec("gymnax") is None:
        return False
    try:
        import gymnax
    except ImportError:
        return False
    if not hasattr(gymnax, "register"):
        return False
    if ENV_ID not in gymnax.registered_envs:
        gymnax.register(ENV_ID, _make_gymnax_env)
    return True
