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
* ``policy_as_controller(fn, **config)``: a policy trained on the environment elsewhere, as a ``Controller``
  judged like jaxtraffic's own (``simulate``, ``evaluate.py --controller``); and the other way round,
  ``runs.ppo.export.load_predict(run_dir)``: a trained run's policy as a plain ``predict(obs) -> a``.

Common to all of them:

* Action: **normalised gains** a in [-1, 1]^3 (clipped), the target gains are gain_max * a
  (``normalised_to_action`` maps a to the environment's pre-tanh action, arctanh(a)). This is the
  box SB3's and rejax's Gaussian policies expect (they clip to it).
* Observation: ``learn.env.observe`` (``control.gain_policy.policy_features``), float32, unbounded.
* Reward, termination (the plant left the physical region, reward -diverge_penalty) and
  truncation (``horizon`` steps) are ``learn.env.step_env``'s; so is the automatic reset, which
  reuses the delay buffer's storage (O(n), not the O(capacity n) of a fresh reset).
* Configuration: ``env_params=`` an ``EnvParams``, or keyword arguments naming fields of the
  training config tree (``runs.config.TrainConfig``: ``n_points``, ``delay``, ``horizon_s``,
  ``delay_spread``, ``gain_max``, ...), so an environment built here is the one ``jaxtraffic-train``
  trains on with the same flags. No arguments: the training defaults (201 points, D = 4 s +- 1 s).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from jaxtraffic._registration import ENV_ID, register_gymnasium
from jaxtraffic.control.adapter import ControllerGrid
from jaxtraffic.control.base import Controller
from jaxtraffic.control.gain_policy import ACTION_EPS, function_controller, normalised_to_action
from jaxtraffic.ecosystem.normalization import active, normalized_policy
from jaxtraffic.learn import env as learn_env
from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.config.checks import check_initial_amplitudes
from jaxtraffic.runs.config.tree import flag_tables

N_GAINS = learn_env.TrafficEnv.action_size

__all__ = ["ACTION_EPS", "ENV_ID", "N_GAINS", "controller_grid", "resolve_env_params", "normalised_to_action",
           "policy_as_controller", "register_gymnasium"]


ENV_SECTIONS = ("plant", "env")  # the config sections an environment reads


def resolve_env_params(env_params: learn_env.EnvParams | None = None, **config: Any) -> learn_env.EnvParams:
    """``env_params`` itself, or the environment that ``train.py ppo`` with the flags ``config`` trains on
    (keywords named as its flags: ``n_points=21, horizon_s=1.0``; the training defaults for the fields not given,
    validated by the config and against the plant)."""
    if env_params is not None:
        if config:
            raise TypeError(f"give env_params or config fields, not both (got {sorted(config)})")
        return env_params
    try:
        tables = flag_tables("ppo", config)
    except TypeError as err:
        raise TypeError(f"unknown environment config field: {err} (the fields are train.py ppo's flags)") from None
    other = sorted((k, s) for s, t in tables.items() if s not in ENV_SECTIONS for k in t)
    if other:  # (lr, out_dir, total_steps: the training's, which the environment never reads)
        name, section = other[0]
        raise TypeError(f"{name!r} is a setting of the training ([{section}]), not of the environment: its keywords "
                        f"are the fields of {' and '.join(ENV_SECTIONS)}")
    train_config = TrainConfig.make(**tables)
    env_params = train_config.env_params()
    check_initial_amplitudes(train_config, env_params.traffic)
    return env_params


def policy_as_controller(fn: Callable[[Any], Any], env_params: learn_env.EnvParams | None = None, *, host: bool = True,
                         batched: bool = False, name: str = "external", **config: Any) -> Controller:
    """A policy trained on this environment elsewhere (Stable-Baselines3, rejax, a gymnax PPO, ...) as a
    ``Controller`` that ``simulate``, ``simulate_batch`` and ``evaluate.py --controller`` judge like
    jaxtraffic's own: ``fn(obs) -> a`` maps the environment's observation to its action, normalised gains
    in [-1, 1]^3 (e.g. ``lambda o: model.predict(o, deterministic=True)[0]``). ``env_params`` / ``config``:
    the environment it was trained on (as for ``GainEnv``); the controller acts on that environment's grid
    (``controller_grid``) with its gain bound, filter and observation. ``host`` and ``batched``: see
    ``control.gain_policy.function_controller`` (``host=False`` for a JAX function). Built inside
    ``normalization.applying(stats)`` (``evaluate.py --controller-normalization``), ``fn`` sees observations
    normalised as SB3's ``VecNormalize`` did in training (host functions only)."""
    ep = resolve_env_params(env_params, **config)
    if active() is not None and not host:
        raise ValueError("--controller-normalization applies to host policies (host=True) only")
    fn = normalized_policy(fn, active())  # evaluate.py --controller-normalization (ecosystem.normalization)
    return function_controller(fn, ep.gain_max, gain_filter=ep.gain_filter, obs_segments=ep.obs_segments,
                               sigma_nodes=ep.filter_nodes, host=host, batched=batched, name=name)


def controller_grid(env_params: learn_env.EnvParams | None = None, **config: Any) -> ControllerGrid:
    """The grid a controller of this environment acts on (its plant's points, period and delay buffer)."""
    return ControllerGrid.of(resolve_env_params(env_params, **config).traffic)
