"""The gain environment (``learn.env``) for other RL ecosystems; each adapter is an optional extra.

* ``ecosystem.gymnax_env.GainGymnaxEnv`` (``pip install jaxtraffic[gymnax]``): a subclass of
  gymnax's ``Environment`` for JAX trainers (purejaxrl-style loops, rejax) and gymnax's wrappers.
* ``ecosystem.gym_env.GainEnv`` / ``GainVectorEnv`` (``[gym]``): a ``gymnasium.Env`` and a batched
  ``gymnasium.vector.VectorEnv`` (one jit-compiled, vmapped step for all environments; numpy in and
  out), registered as ``"jaxtraffic/Gain-v0"`` by ``import jaxtraffic`` when gymnasium is installed
  (``jaxtraffic._registration``)::

      import gymnasium, jaxtraffic
      env = gymnasium.make("jaxtraffic/Gain-v0", n_points=51)
      venv = gymnasium.make_vec("jaxtraffic/Gain-v0", num_envs=256, vectorization_mode="vector_entry_point")
      # without importing jaxtraffic first: gymnasium.make("jaxtraffic:jaxtraffic/Gain-v0")

* ``ecosystem.sb3.SB3VecEnv`` (``[sb3]``): the vector environment as a Stable-Baselines3 ``VecEnv``.

Common to all of them:

* Action: **normalised gains** a in [-1, 1]^3 (clipped), the target gains are gain_max * a
  (``normalised_to_action`` maps a to the environment's pre-tanh action, arctanh(a)). This is the
  box SB3's and rejax's Gaussian policies expect (they clip to it).
* Observation: ``learn.env.observe`` (``control.gain_policy.policy_features``), float32, unbounded.
* Reward, termination (the plant left the physical region, reward -diverge_penalty) and
  truncation (``horizon`` steps) are ``learn.env.step_env``'s; so is the automatic reset, which
  reuses the delay buffer's storage (O(n), not the O(capacity n) of a fresh reset).
* Configuration: ``env_params=`` an ``EnvParams``, or keyword arguments naming fields of the
  training config tree (``learn.config.TrainConfig``: ``n_points``, ``delay``, ``horizon_s``,
  ``delay_spread``, ``gain_max``, ...), so an environment built here is the one ``jaxtraffic-train``
  trains on with the same flags. No arguments: the training defaults (201 points, D = 4 s +- 1 s).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxtraffic._registration import ENV_ID, register_gymnasium
from jaxtraffic.learn import env as E

N_GAINS = E.GainEnv.action_size
# a = +-1 would be an infinite pre-tanh action; the largest |a| used is 1 - ACTION_EPS
ACTION_EPS = 1e-6

__all__ = ["ACTION_EPS", "ENV_ID", "N_GAINS", "make_env_params", "normalised_to_action", "register_gymnasium"]


def make_env_params(env_params: E.EnvParams | None = None, **config: Any) -> E.EnvParams:
    """``env_params`` itself, or the environment of ``TrainConfig.from_flat(**config)`` (the training
    defaults for the fields not given; ``learn.trainer.build`` validates them)."""
    if env_params is not None:
        if config:
            raise TypeError(f"give env_params or config fields, not both (got {sorted(config)})")
        return env_params
    from jaxtraffic.learn.config import TrainConfig
    from jaxtraffic.learn.trainer import build

    return build(TrainConfig.from_flat(**config))[1]


def normalised_to_action(a: jax.Array) -> jax.Array:
    """The environment's action (pre-tanh, ``learn.env.action_to_gains``) for normalised gains ``a``
    in [-1, 1]^3 (clipped): target gains = gain_max * a, up to float rounding."""
    a = jnp.clip(jnp.asarray(a, jnp.float32), -1.0, 1.0)
    return jnp.arctanh(a * (1.0 - ACTION_EPS))
