"""The gain environment for Gymnasium (``pip install jaxtraffic[gym]``): ``GainEnv`` (a
``gymnasium.Env``) and ``GainVectorEnv`` (a batched ``gymnasium.vector.VectorEnv``), registered as
``"jaxtraffic/Gain-v0"`` (entry point and vector entry point) by ``import jaxtraffic``.

Both are numpy in, numpy out, over ``learn.env``'s pure functions:

* ``GainEnv``: one environment, a jit-compiled step per call. Seeded by ``reset(seed=...)``
  (``np_random`` draws the JAX key of the episode); the observation returned with
  ``terminated``/``truncated`` is the episode's last one (call ``reset`` next, as Gymnasium asks).
* ``GainVectorEnv(num_envs)``: every call steps all environments with **one** jit-compiled,
  vmapped ``learn.env.step_env`` (no Python loop over environments). Autoreset mode
  ``SAME_STEP``: a finished environment is reset within the same ``step`` (``learn.env``'s cheap
  reset), its returned observation is the new episode's first, and ``info["final_obs"]`` (an object
  array, ``None`` elsewhere, mask ``info["_final_obs"]``) holds the last observation of the
  finished episode: bootstrap a truncated step from it. ``info["gains"]`` holds the applied gains.

Spaces (see ``jaxtraffic.ecosystem``): action ``Box(-1, 1, (3,))``, normalised gains (target gains
= gain_max * a); observation ``Box(-inf, inf, (obs_size,))``, float32. Keyword arguments name
fields of the training config tree (``n_points=21``, ``delay=2.0``, ``horizon_s=10``, ...), or give
``env_params=``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from jaxtraffic.ecosystem import N_GAINS, make_env_params, normalised_to_action
from jaxtraffic.learn import env as E

__all__ = ["GainEnv", "GainVectorEnv"]


def _spaces(params: E.EnvParams) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-np.inf, np.inf, (E.obs_size(params),), np.float32)
    act = spaces.Box(-1.0, 1.0, (N_GAINS,), np.float32)
    return obs, act


def _key_from(rng: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(rng.integers(0, 2**31 - 1)))


def _step(key, state, action, params):
    """(next key, obs, state, reward, terminated, truncated, final obs, gains): one step, key split inside."""
    key, k = jax.random.split(key)
    obs, state, reward, _, info = E.step_env(k, state, normalised_to_action(action), params)
    return key, obs, state, reward, info["terminated"], info["truncated"], info["terminal_obs"], info["gains"]


def _reset(key, params):
    key, k = jax.random.split(key)
    obs, state = E.reset_env(k, params)
    return key, obs, state


class GainEnv(gym.Env):
    """One traffic gain environment (``learn.env``) as a ``gymnasium.Env``."""

    metadata = {"render_modes": []}

    def __init__(self, env_params: E.EnvParams | None = None, render_mode: str | None = None, **config: Any):
        if render_mode is not None:
            raise ValueError(f"no render modes, got render_mode={render_mode!r}")
        self.env_params = make_env_params(env_params, **config)
        self.observation_space, self.action_space = _spaces(self.env_params)
        self._reset_fn = jax.jit(_reset)
        self._step_fn = jax.jit(_step)
        self._key = self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._key, obs, self._state = self._reset_fn(_key_from(self.np_random), self.env_params)
        return np.array(obs), {}

    def step(self, action):
        if self._state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        action = jnp.asarray(np.asarray(action, np.float32).reshape(N_GAINS))
        self._key, _, self._state, r, term, trunc, final_obs, gains = self._step_fn(
            self._key, self._state, action, self.env_params)
        return np.array(final_obs), float(r), bool(term), bool(trunc), {"gains": np.array(gains)}


class GainVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` traffic gain environments stepped together by one jit-compiled vmapped step."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int = 16, env_params: E.EnvParams | None = None, render_mode: str | None = None,
                 **config: Any):
        if render_mode is not None:
            raise ValueError(f"no render modes, got render_mode={render_mode!r}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = int(num_envs)
        self.env_params = make_env_params(env_params, **config)
        self.single_observation_space, self.single_action_space = _spaces(self.env_params)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        n = self.num_envs

        def reset_all(key, params):
            key, k = jax.random.split(key)
            obs, state = jax.vmap(E.reset_env, (0, None))(jax.random.split(k, n), params)
            return key, obs, state

        def step_all(key, state, action, params):
            key, k = jax.random.split(key)
            out = jax.vmap(_step, (0, 0, 0, None))(jax.random.split(k, n), state, action, params)
            return (key,) + out[1:]

        self._reset_fn = jax.jit(reset_all)
        self._step_fn = jax.jit(step_all, donate_argnums=1)  # the batch's delay buffers are updated in place
        self._key = self._state = None

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Reset every environment; ``seed`` (an int, or a list whose first entry is used) seeds the
        JAX key of all of them."""
        if isinstance(seed, (list, tuple)):
            seed = None if seed[0] is None else int(seed[0])
        super().reset(seed=seed)
        self._key, obs, self._state = self._reset_fn(_key_from(self.np_random), self.env_params)
        return np.array(obs), {}

    def step(self, actions):
        if self._state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        actions = jnp.asarray(np.asarray(actions, np.float32).reshape(self.num_envs, N_GAINS))
        self._key, obs, self._state, r, term, trunc, final_obs, gains = self._step_fn(
            self._key, self._state, actions, self.env_params)
        term, trunc = np.array(term), np.array(trunc)  # np.array: writable copies (SB3 edits rewards in place)
        infos: dict[str, Any] = {"gains": np.asarray(gains), "_gains": np.ones(self.num_envs, bool)}
        done = term | trunc
        if done.any():
            final = np.asarray(final_obs)
            fo = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(done):
                fo[i] = final[i]
            infos.update(final_obs=fo, _final_obs=done, final_info={}, _final_info=done)
        return np.array(obs), np.array(r, np.float32), term, trunc, infos

    def close_extras(self, **kwargs):
        self._state = None
