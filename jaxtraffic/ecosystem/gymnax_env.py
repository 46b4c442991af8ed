"""The gain environment as a gymnax ``Environment`` (``pip install jaxtraffic[gymnax]``).

``GainGymnaxEnv`` subclasses ``gymnax.environments.environment.Environment``: ``default_params``,
``observation_space``/``action_space`` (gymnax ``Box``es), ``num_actions`` (3), ``name``, and gymnax
1.0's six-value ``step`` -> ``(obs, state, reward, terminated, truncated, info)`` with
``info["final_observation"]`` (the observation before the automatic reset: bootstrap a truncated
step from it). It overrides ``step`` rather than implementing ``step_env`` alone: gymnax's generic
``step`` would draw a second, full reset every step, while ``learn.env.step_env`` resets finished
environments itself, reusing the delay buffer (O(n) per step). gymnax's wrappers
(``LogWrapper``, ``FlattenObservationWrapper``, ...) work on it under ``vmap`` and ``scan``;
``examples/gymnax_ppo.py`` trains it with a purejaxrl-style PPO written against gymnax alone.

Actions are normalised gains in [-1, 1]^3 (see ``jaxtraffic.ecosystem``); ``raw_actions=True``
takes the environment's own unbounded pre-tanh action instead (``learn.env.action_to_gains``), for a
policy that squashes itself.

Importing this module registers the environment with gymnax: ``gymnax.make("jaxtraffic/Gain-v0",
n_points=21)`` returns ``(GainGymnaxEnv(n_points=21), its default params)`` (``_registration``).
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from gymnax.environments import environment, spaces

from jaxtraffic._registration import register_gymnax
from jaxtraffic.ecosystem import ENV_ID, N_GAINS, normalised_to_action, resolve_env_params
from jaxtraffic.learn import env as learn_env

__all__ = ["GainGymnaxEnv"]


class GainGymnaxEnv(environment.Environment[learn_env.EnvState, learn_env.EnvParams]):
    """gymnax view of ``learn.env`` (state ``EnvState``, params ``EnvParams``).

    ``GainGymnaxEnv(env_params=None, raw_actions=False, **config)``: ``config`` names fields of
    ``runs.config.TrainConfig`` (``n_points=21``, ``horizon_s=10``, ...), see ``jaxtraffic.ecosystem``.
    """

    def __init__(self, env_params: learn_env.EnvParams | None = None, raw_actions: bool = False, **config: Any):
        super().__init__()
        self._params = resolve_env_params(env_params, **config)
        self.raw_actions = raw_actions

    @property
    def default_params(self) -> learn_env.EnvParams:
        return self._params

    @property
    def name(self) -> str:
        return ENV_ID

    @property
    def num_actions(self) -> int:
        return N_GAINS

    def _action(self, action: jax.Array) -> jax.Array:
        action = jnp.asarray(action, jnp.float32)
        return action if self.raw_actions else normalised_to_action(action)

    @partial(jax.jit, static_argnames=("self",))
    def step(self, key: jax.Array, state: learn_env.EnvState, action: jax.Array,
             params: learn_env.EnvParams | None = None):
        """One dt (``learn.env.step_env``, its own cheap automatic reset); gymnax 1.0's six values."""
        params = self.default_params if params is None else params
        obs, state, reward, _, info = learn_env.step_env(key, state, self._action(action), params)
        info = {"final_observation": info["terminal_obs"], "terminated": info["terminated"],
                "truncated": info["truncated"], "gains": info["gains"],
                "discount": 1.0 - info["terminated"].astype(jnp.float32)}
        return obs, state, reward, info["terminated"], info["truncated"], info

    def step_env(self, key: jax.Array, state: learn_env.EnvState, action: jax.Array, params: learn_env.EnvParams):
        """gymnax's five-value hook (for code that calls it directly); ``step`` does not use it."""
        obs, state, reward, terminated, _, info = self.step(key, state, action, params)
        return obs, state, reward, terminated, info

    def reset_env(self, key: jax.Array, params: learn_env.EnvParams):
        return learn_env.reset_env(key, params)

    def get_obs(self, state: learn_env.EnvState, params: learn_env.EnvParams | None = None,
                key: jax.Array | None = None):
        return learn_env.observe(state, self.default_params if params is None else params)

    def is_truncated(self, state: learn_env.EnvState, params: learn_env.EnvParams) -> jax.Array:
        return state.t >= params.horizon

    def is_terminated(self, state: learn_env.EnvState, params: learn_env.EnvParams) -> jax.Array:
        return state.plant.diverged

    def observation_space(self, params: learn_env.EnvParams | None = None) -> spaces.Box:
        params = self.default_params if params is None else params
        return spaces.Box(-jnp.inf, jnp.inf, (learn_env.obs_size(params),), jnp.float32)

    def action_space(self, params: learn_env.EnvParams | None = None) -> spaces.Box:
        if self.raw_actions:
            return spaces.Box(-jnp.inf, jnp.inf, (N_GAINS,), jnp.float32)
        return spaces.Box(-1.0, 1.0, (N_GAINS,), jnp.float32)


register_gymnax()  # gymnax.make(ENV_ID, **config) (gymnax is imported above)
