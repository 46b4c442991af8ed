"""Per-member views and edits of a PPO ``Runner`` whose leaves carry (device, seed, ...) axes.

``replicated`` reads the leaves every device shares (parameters, optimiser state, statistics) as
host arrays; ``restart_members`` replaces some members (seeds) by those of a fresh runner. Both
work with a runner sharded over a mesh that spans several processes (``learn.ppo.algorithm.train_mesh``):
every process calls them at the same point.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from jaxtraffic.learn.ppo.algorithm import Runner
from jaxtraffic.sim.sharding import local_copy

__all__ = ["replicated", "restart_members"]


def restart_members(runner: Runner, fresh: Runner, members: np.ndarray) -> Runner:
    """``runner`` with the seeds (members) where ``members`` (shape (num_seeds,), bool) is True
    replaced by those of ``fresh`` (e.g. ``init`` of a new key): network, optimiser state,
    environments, observation statistics, key and update count. Same placement as ``runner`` (a
    jit-compiled select: with a mesh over several processes every process calls it)."""
    mask = jnp.asarray(np.asarray(members, bool))

    def pick(old, new):
        return jnp.where(mask.reshape((1, -1) + (1,) * (old.ndim - 2)), new, old)  # (device, seed, ...)

    return jax.jit(lambda r, f: jax.tree.map(pick, r, f))(runner, fresh)


def replicated(runner: Runner) -> Runner:
    """The device-0 copy of the replicated leaves (params, optimiser state, statistics, key, update
    count), per seed, as numpy arrays (usable with any devices); ``env_state`` and ``obs``, which
    differ between devices, are None. With a runner sharded over a mesh this is one small
    jit-compiled broadcast (a collective when the mesh spans processes: every process calls it)."""
    shared = runner.replace(env_state=None, obs=None)
    sharding = getattr(jax.tree_util.tree_leaves(shared)[0], "sharding", None)
    if not isinstance(sharding, NamedSharding):  # host arrays
        return jax.tree.map(lambda x: np.asarray(x[0]), shared)
    return jax.device_get(local_copy(_first_device_fn(sharding.mesh)(shared)))


@functools.cache
def _first_device_fn(mesh: Mesh):
    return jax.jit(lambda tree: jax.tree.map(lambda x: x[0], tree), out_shardings=NamedSharding(mesh, P()))
