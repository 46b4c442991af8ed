"""Gymnasium registration of the gain environment, run at ``import jaxtraffic``.

Gymnasium 1.x has no plugin (entry-point) registration, so ``gymnasium.make("jaxtraffic/Gain-v0")``
finds the id only once a module has called ``gymnasium.register``. ``import jaxtraffic`` does it
when gymnasium is installed (``find_spec``: nothing is imported when it is not), with string entry
points, so ``jaxtraffic.ecosystem.gym_env`` (and ``learn.env``) are imported only by ``make``.
Cost: the import of gymnasium itself, ~60 ms after jax (docs/model.md section 19.4).
The module-prefixed id ``"jaxtraffic:jaxtraffic/Gain-v0"`` needs no import first: gymnasium imports
``jaxtraffic``, which registers the id.
"""

from __future__ import annotations

import importlib.util

ENV_ID = "jaxtraffic/Gain-v0"

__all__ = ["ENV_ID", "register_gymnasium"]


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
