"""The gain environment for Gymnasium (``pip install jaxtraffic[gym]``): ``GainEnv`` (a
``gymnasium.Env``) and ``GainVectorEnv`` (a batched ``gymnasium.vector.VectorEnv``), registered as
``"jaxtraffic/Gain-v0"`` (entry point and vector entry point) by ``import jaxtraffic``.

Both are numpy in, numpy out, over ``learn.env``'s pure functions:

* ``GainEnv``: one environment, a jit-compiled step per call. Seeded by ``reset(seed=...)``
  (``np_random`` draws the JAX key of the episode); the observation returned with
  ``terminated``/``truncated`` is the episode's last one (call ``reset`` next, as Gymnasium asks).
* ``GainVectorEnv(num_envs)``: every call steps all environments with **one** jit-compiled,
  vmapped ``learn.env.step_env`` (no Python loop over environments); each environment has its own
  JAX key. ``autoreset_mode``:

  - ``NEXT_STEP`` (the default, Gymnasium's): a finished environment returns its episode's last
    observation; the next ``step`` resets it (its action is ignored, reward 0, not done) and
    returns the new episode's first. Gymnasium's vector wrappers (``NormalizeObservation``, ...)
    ask for this mode.
  - ``SAME_STEP``: a finished environment is reset within the same ``step`` (``learn.env``'s cheap
    reset), its returned observation is the new episode's first, and ``info["final_obs"]`` (an object
    array, ``None`` elsewhere, mask ``info["_final_obs"]``) holds the last observation of the
    finished episode (``SB3VecEnv`` uses this mode).

  ``reset(seed=...)`` (ints >= 0; ``num_envs`` an int >= 1): an int seeds every environment, a list one
  seed per environment;
  ``reset(options={"reset_mask": mask})`` resets only the environments where ``mask`` is True (the
  others keep their episode; all observations are returned). ``info["gains"]`` holds the applied gains.

``render_mode="rgb_array"``: ``render()`` returns the episode's density as a space-time picture
(``ecosystem.render``; the vector environment: one per environment, a tuple), e.g. for
``gymnasium.wrappers.RecordVideo`` (``metadata["render_fps"]``: real time, 1 / dt).

Spaces (see ``jaxtraffic.ecosystem``): action ``Box(-1, 1, (3,))``, normalised gains (target gains
= gain_max * a; a finite action outside the box is clipped to it, a NaN or infinite one is refused with a
``ValueError`` before the step: it would poison the state and every later observation); observation
``Box(-inf, inf, (obs_size,))``, float32. Keyword arguments name
fields of the training config tree (``n_points=21``, ``delay=2.0``, ``horizon_s=10``, ...), or give
``env_params=``.

Processes: the environments hold JAX state, and JAX is not fork-safe. For Gymnasium's
``AsyncVectorEnv`` / SB3's ``SubprocVecEnv`` use ``context="forkserver"`` (or ``"spawn"``) and the
module-prefixed id ``"jaxtraffic:jaxtraffic/Gain-v0"`` (a new process imports jaxtraffic, which
registers the id); with ``fork`` the children hang. ``forkserver`` and ``spawn`` start the children by
importing the parent's main module: a script must create the vector environment under
``if __name__ == "__main__":`` (otherwise each child runs the script again and Python raises "An attempt has
been made to start a new process before the current process has finished its bootstrapping phase").
``GainVectorEnv`` already steps the whole batch in one compiled call and is the faster choice on one machine.

``RecordVideo`` writes its videos with moviepy (in the ``[gym]`` extra).
"""

from __future__ import annotations

import numbers
from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from jaxtraffic.ecosystem import N_GAINS, normalised_to_action, resolve_env_params
from jaxtraffic.ecosystem.render import History, spacetime_rgb
from jaxtraffic.learn import env as learn_env
from jaxtraffic.model.params import equilibrium

__all__ = ["GainEnv", "GainVectorEnv", "RENDER_MODES"]

RENDER_MODES = ["rgb_array"]


def _spaces(params: learn_env.EnvParams) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-np.inf, np.inf, (learn_env.obs_size(params),), np.float32)
    act = spaces.Box(-1.0, 1.0, (N_GAINS,), np.float32)
    return obs, act


def _key_from(rng: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(rng.integers(0, 2**31 - 1)))


def _check_render_mode(render_mode: str | None) -> str | None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES} or None, got {render_mode!r}")
    return render_mode


def _metadata(params: learn_env.EnvParams, **extra: Any) -> dict[str, Any]:
    return {"render_modes": RENDER_MODES, "render_fps": round(1.0 / float(params.traffic.dt)), **extra}


def _is_int(x: object) -> bool:
    """An integer, numpy's included, not a bool. A plain predicate, not an ``isinstance`` in place: mypy takes
    ``isinstance(n, numbers.Integral)`` of an ``int`` n for False (and the code after a failed check for dead)."""
    return isinstance(x, numbers.Integral) and not isinstance(x, (bool, np.bool_))


def _check_seed(seed: Any, what: str = "seed") -> None:
    """ValueError unless ``seed`` is None or an int in [0, 2**63) (Gymnasium's rule; 1.5 or -1 are refused)."""
    if seed is not None and not (_is_int(seed) and 0 <= seed < 2**63):
        raise ValueError(f"{what} must be None or an int >= 0, got {seed!r}")


def _action(action: Any, shape: tuple[int, ...]) -> jax.Array:
    """The action as float32 of ``shape``; ValueError for a NaN or infinite entry (it would poison the state and
    every observation after it): a finite action outside [-1, 1] is clipped to the action space by the step."""
    if np.iscomplexobj(action) or not np.issubdtype(np.asarray(action).dtype, np.number):
        raise ValueError(f"the action must be real numbers, got {np.asarray(action).tolist()!r} (dtype "
                         f"{np.asarray(action).dtype}); the action space is Box(-1, 1)")
    a = np.asarray(action, np.float32).reshape(shape)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"the action must be finite, got {np.asarray(action).tolist()!r} (NaN or inf; a policy "
                         "that diverged?); the action space is Box(-1, 1)")
    return jnp.asarray(a)


def _step(key, state, action, params):
    """(next key, obs, state, reward, terminated, truncated, final obs, gains, final density): one step."""
    key, k = jax.random.split(key)
    obs, state, reward, _, info = learn_env.step_env(k, state, normalised_to_action(action), params)
    return (key, obs, state, reward, info["terminated"], info["truncated"], info["terminal_obs"], info["gains"],
            info["terminal_rho"])


def _reset(key, params):
    key, k = jax.random.split(key)
    obs, state = learn_env.reset_env(k, params)
    return key, obs, state


class GainEnv(gym.Env):
    """One traffic gain environment (``learn.env``) as a ``gymnasium.Env``."""

    metadata = {"render_modes": RENDER_MODES}

    def __init__(self, env_params: learn_env.EnvParams | None = None, render_mode: str | None = None, **config: Any):
        self.render_mode = _check_render_mode(render_mode)
        self.env_params = resolve_env_params(env_params, **config)
        self.metadata = _metadata(self.env_params)
        self.observation_space, self.action_space = _spaces(self.env_params)
        self._reset_fn = jax.jit(_reset)
        self._step_fn = jax.jit(_step)
        self._key: jax.Array | None = None
        self._state: Any = None  # (a learn_env.EnvState once reset)
        self._history = History(1, self.env_params.horizon, self.env_params.traffic.n_points) if render_mode else None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        _check_seed(seed)
        super().reset(seed=seed)
        self._key, obs, self._state = self._reset_fn(_key_from(self.np_random), self.env_params)
        if self._history is not None:
            self._history.start(np.array([0]), np.asarray(self._state.plant.rho)[None])
        return np.array(obs), {}

    def step(self, action):
        if self._state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        action = _action(action, (N_GAINS,))
        self._key, _, self._state, r, term, trunc, final_obs, gains, rho = self._step_fn(
            self._key, self._state, action, self.env_params)
        if self._history is not None:
            self._history.record(np.array([0]), np.asarray(rho)[None])
        return np.array(final_obs), float(r), bool(term), bool(trunc), {"gains": np.array(gains)}

    def render(self) -> np.ndarray | None:
        """The episode's density as a space-time picture (``render_mode="rgb_array"``), else None."""
        if self._history is None:
            return None
        return spacetime_rgb(self._history.rho[0], float(equilibrium(self.env_params.traffic)[0]))


def _autoreset_mode(mode: AutoresetMode | str) -> AutoresetMode:
    """``NEXT_STEP`` or ``SAME_STEP``, given as the enumeration, its name or its value."""
    given = mode
    if isinstance(mode, str) and mode in AutoresetMode.__members__:
        mode = AutoresetMode[mode]
    try:
        resolved: AutoresetMode | None = AutoresetMode(mode)
    except ValueError:
        resolved = None
    if resolved is None or resolved not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
        raise ValueError(f"autoreset_mode must be NEXT_STEP or SAME_STEP, got {given!r}")
    return resolved


def _keep(hold: jax.Array, old: Any, new: Any) -> Any:
    """``old`` where ``hold`` (one flag per environment), else ``new``, leaf by leaf."""
    return jax.tree.map(lambda a, b: jnp.where(hold.reshape(hold.shape + (1,) * (a.ndim - 1)), a, b), old, new)


class GainVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` traffic gain environments stepped together by one jit-compiled vmapped step."""

    metadata = {"render_modes": RENDER_MODES, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 16, env_params: learn_env.EnvParams | None = None,
                 render_mode: str | None = None, autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                 **config: Any):
        self.render_mode = _check_render_mode(render_mode)
        if not _is_int(num_envs) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        mode = _autoreset_mode(autoreset_mode)
        self.num_envs = int(num_envs)
        self.env_params = resolve_env_params(env_params, **config)
        self.metadata = _metadata(self.env_params, autoreset_mode=mode)
        self.single_observation_space, self.single_action_space = _spaces(self.env_params)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

        def step_all(keys, state, action, params, hold):
            out = jax.vmap(_step, (0, 0, 0, None))(keys, state, action, params)
            # held environments (NEXT_STEP: finished at the last step) already hold their next episode
            return out[:2] + (_keep(hold, state, out[2]),) + out[3:]

        self._reset_fn = jax.jit(jax.vmap(_reset, (0, None)))
        self._step_fn = jax.jit(step_all, donate_argnums=1)  # the batch's delay buffers are updated in place
        self._keys: jax.Array | None = None  # (set by reset: batched keys, states and observations)
        self._state: Any = None
        self._obs: Any = None
        self._hold = np.zeros(self.num_envs, bool)  # NEXT_STEP: reset at the next step
        self._next_obs: Any = None  # NEXT_STEP: the first observations of the held environments' next episodes
        tp = self.env_params.traffic
        self._history = History(self.num_envs, self.env_params.horizon, tp.n_points) if render_mode else None

    def _seed_keys(self, seed: int | list | tuple | None) -> jax.Array:
        n = self.num_envs
        if isinstance(seed, (list, tuple)):
            if len(seed) != n:
                raise ValueError(f"one seed per environment: got {len(seed)} seeds for {n} environments")
            return jnp.stack([_key_from(self.np_random) if s is None else jax.random.PRNGKey(int(s)) for s in seed])
        return jax.random.split(jax.random.PRNGKey(int(seed)) if seed is not None else _key_from(self.np_random), n)

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        """Reset the environments (those of ``options["reset_mask"]``, else all). ``seed``: an int seeds
        them all (one key split per environment), a list one seed each (None: drawn)."""
        for i, s in enumerate(seed if isinstance(seed, (list, tuple)) else [seed]):
            _check_seed(s, f"seed[{i}]" if isinstance(seed, (list, tuple)) else "seed")
        super().reset(seed=seed if isinstance(seed, int) else None)
        mask = (options or {}).get("reset_mask")
        if mask is not None:
            mask = np.asarray(mask, bool)
            if mask.shape != (self.num_envs,):
                raise ValueError(f"reset_mask must have shape ({self.num_envs},), got {mask.shape}")
        keys, obs, state = self._reset_fn(self._seed_keys(seed), self.env_params)
        obs = np.array(obs)
        if mask is None or self._state is None:
            mask = np.ones(self.num_envs, bool)
            self._keys, self._state, self._obs = keys, state, obs
        else:
            m = jnp.asarray(mask)
            self._keys, self._state = _keep(m, keys, self._keys), _keep(m, state, self._state)
            self._obs = np.where(mask[:, None], obs, self._obs)
        self._hold &= ~mask
        if self._history is not None:
            self._history.start(np.flatnonzero(mask), np.asarray(self._state.plant.rho)[mask])
        return self._obs.copy(), {}

    def step(self, actions):
        if self._state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        actions = _action(actions, (self.num_envs, N_GAINS))
        hold = self._hold
        self._keys, obs, self._state, r, term, trunc, final_obs, gains, rho = self._step_fn(
            self._keys, self._state, actions, self.env_params, jnp.asarray(hold))
        # np.array: writable copies (SB3 edits rewards in place)
        obs, r, term, trunc, gains = (np.array(x) for x in (obs, r, term, trunc, gains))
        r = r.astype(np.float32)
        infos: dict[str, Any] = {}
        if self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP:
            term[hold], trunc[hold], r[hold], gains[hold] = False, False, 0.0, 0.0
            done = term | trunc
            first, self._next_obs = self._next_obs, obs  # a finished environment's next episode starts at obs
            obs = np.where(done[:, None], np.asarray(final_obs), obs)
            if hold.any():
                obs[hold] = first[hold]
            self._hold = done
        else:
            done = term | trunc
            if done.any():
                final = np.asarray(final_obs)
                fo = np.full(self.num_envs, None, dtype=object)
                for i in np.flatnonzero(done):
                    fo[i] = final[i]
                infos.update(final_obs=fo, _final_obs=done, final_info={}, _final_info=done)
        infos.update(gains=gains, _gains=np.ones(self.num_envs, bool))
        if self._history is not None:
            self._record(hold, done, np.asarray(rho))
        self._obs = obs
        return obs.copy(), r, term, trunc, infos

    def _record(self, hold: np.ndarray, done: np.ndarray, rho: np.ndarray) -> None:
        h = self._history
        assert h is not None  # step() records only with a render_mode
        stepped = np.flatnonzero(~hold)
        h.record(stepped, rho[stepped])
        restart = hold if self.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP else done
        if restart.any():
            h.start(np.flatnonzero(restart), np.asarray(self._state.plant.rho)[restart])

    def render(self) -> tuple[np.ndarray, ...] | None:
        """Each environment's episode as a space-time picture (``render_mode="rgb_array"``), else None."""
        if self._history is None:
            return None
        rho_bar = float(equilibrium(self.env_params.traffic)[0])
        return tuple(spacetime_rgb(hist, rho_bar) for hist in self._history.rho)

    def close_extras(self, **kwargs):
        self._state = None
