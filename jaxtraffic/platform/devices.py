"""One XLA CPU device per core: ``split_host_devices()``, called by the command lines before jax starts.

XLA's CPU backend presents the whole host as ONE device, and a jit-compiled batched rollout on
one device keeps about one core busy. The command lines (``train.py``, ``evaluate.py``,
``jaxtraffic-train``, ``python -m jaxtraffic``) call ``split_host_devices()`` when ``jaxtraffic.cli``
is imported; ``import jaxtraffic`` itself changes nothing in the process (a library must not change
``jax.local_device_count()`` for every other library). A program of your own may call
``jaxtraffic.split_host_devices()`` first thing, before any JAX computation, for the same split.
It does nothing when

  * ``JAXTRAFFIC_NO_DEVICE_SPLIT`` is set to a non-empty value other than ``0`` (opt-out),
  * the user's ``XLA_FLAGS`` already contain ``--xla_force_host_platform_device_count``
    (or ``JAX_NUM_CPU_DEVICES`` is set), or
  * jax's backends have been initialised already (importing jax first is fine; having called
    ``jax.devices()`` or run a computation is not: the flag would be ignored),

otherwise it appends ``--xla_force_host_platform_device_count=<cores>`` to ``XLA_FLAGS``
(cores: the CPUs this process may run on, ``os.sched_getaffinity``). The flag only shapes the
CPU platform: on a GPU/TPU machine ``jax.devices()`` still lists the accelerators. Nothing is
changed on a one-core machine. What it costs not to split: docs/model.md section 19.1.

The batched entry points (``simulate_batch``, the evaluation, the trainers) shard their batch
over ``jax.devices()``; see ``jaxtraffic.sim.sharding``. A rollout's numbers do not depend on the
device count beyond float32 rounding; a PPO training's do (its minibatches and gradient sums
split over the devices, and the training is chaotic in such rounding): docs/model.md section 19.1
(the default recipe measured on one device and on two).
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

FLAG = "--xla_force_host_platform_device_count"
OPT_OUT = "JAXTRAFFIC_NO_DEVICE_SPLIT"


def host_cores() -> int:
    """CPUs this process may run on (its affinity mask), else ``os.cpu_count()``."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _backends_initialised() -> bool:
    xb = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(xb, "_backends", None)) if xb is not None else False


def split_host_devices(env: MutableMapping[str, str] | None = None) -> int | None:
    """Add the device-count flag to ``env`` (default ``os.environ``) where allowed (see the module
    docstring); return the device count set, or None when nothing was changed. Call it before the
    first JAX computation (importing jax first is fine)."""
    env = os.environ if env is None else env
    if env.get(OPT_OUT, "") not in ("", "0"):
        return None
    flags = env.get("XLA_FLAGS", "")
    if FLAG in flags or env.get("JAX_NUM_CPU_DEVICES") or _backends_initialised():
        return None
    n = host_cores()
    if n <= 1:
        return None
    env["XLA_FLAGS"] = f"{flags} {FLAG}={n}".strip()
    return n

