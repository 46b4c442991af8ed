"""A trained gain policy as a ``Controller`` (shared interface with the baselines).

``policy_controller`` wraps network parameters and observation statistics; ``load_policy``
turns a run directory written by ``train.py`` into a controller (deterministic gains: the mean
of the Gaussian, squashed by ``gain_max * tanh``, then filtered like in the environment, with the
applied gains as the controller state).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxtraffic.controllers import Controller, Observation, gain_law
from jaxtraffic.env import filter_gains, policy_input
from jaxtraffic.networks import ActorCritic
from jaxtraffic.params import TrafficParams, equilibrium
from jaxtraffic.ppo import normalize_obs

Array = jax.Array


@struct.dataclass
class PolicySettings:
    """Traced settings of a policy controller: network parameters, observation mean/variance
    (shape (3 n + 3,)), the gain bound and the gain filter (dimensionless, ``env.filter_gains``)."""

    params: Any
    obs_mean: Array
    obs_var: Array
    gain_max: Array
    gain_filter: Array


def _policy_head(settings: PolicySettings, x: Array, network: ActorCritic) -> tuple[Array, Array]:
    """(mean, sigma) of the pre-squash Gaussian action for a raw observation vector ``x``."""
    mean, sigma, _ = network.apply(settings.params, normalize_obs(x, settings.obs_mean, settings.obs_var))
    return mean, sigma


@functools.cache
def _policy_act_fn(hidden: tuple, activation: str, init_sigma: float, stochastic: bool):
    network = ActorCritic(hidden=hidden, activation=activation, init_sigma=init_sigma)

    def act(settings: PolicySettings, gains_prev, obs, nominal, key):
        x = policy_input(obs.rho, obs.v, obs.h_prev, gains_prev, nominal, settings.gain_max)
        mean, sigma = _policy_head(settings, x, network)
        if stochastic:
            mean = mean + sigma * jax.random.normal(key, mean.shape)
        gains = filter_gains(gains_prev, settings.gain_max * jnp.tanh(mean), settings.gain_filter)
        return gain_law(gains, obs, nominal), gains

    return act


def _zero_gains(settings: PolicySettings, obs, nominal) -> Array:
    return jnp.zeros((3,), obs.rho.dtype)


def policy_controller(params: Any, obs_mean: Array, obs_var: Array, gain_max: float, *,
                      hidden: tuple, activation: str = "tanh", init_sigma: float = 0.5,
                      stochastic: bool = False, gain_filter: float | Array = 1.0) -> Controller:
    """Controller applying the policy's (filtered) gains through the paper's three-gain law;
    its state is the gains applied at the previous step (zero at the start)."""
    settings = PolicySettings(params=params, obs_mean=jnp.asarray(obs_mean), obs_var=jnp.asarray(obs_var),
                              gain_max=jnp.asarray(gain_max, float),
                              gain_filter=jnp.broadcast_to(jnp.asarray(gain_filter, float), jnp.shape(gain_max)))
    act = _policy_act_fn(tuple(hidden), activation, float(init_sigma), stochastic)
    return Controller(settings=settings, act_fn=act, init_fn=_zero_gains, name="ppo")


def equilibrium_gains(controller: Controller, nominal: TrafficParams, n_iter: int = 300) -> Array:
    """Gains (shape (3,), dimensionless) that a policy controller settles to while the plant sits at
    the equilibrium of ``nominal``: the fixed point of its filtered gains, iterated ``n_iter`` steps
    from zero (for a policy whose gains keep cycling there: the gains after ``n_iter`` steps). They
    set the closed loop's asymptotic behaviour (``linear.gain_law_wave_speed``).
    For a controller with batched settings, ``vmap`` over them."""
    rho_bar, v_bar = equilibrium(nominal)
    n = nominal.n_points
    obs = Observation(rho=jnp.full((n,), rho_bar), v=jnp.full((n,), v_bar), h_prev=jnp.full((n,), nominal.h_bar),
                      t=jnp.zeros(()), sent=None)

    def body(_, gains):
        return controller.act_fn(controller.settings, gains, obs, nominal, None)[1]

    return jax.lax.fori_loop(0, n_iter, body, jnp.zeros((3,), obs.rho.dtype))


def load_policy(run_dir: str | Path, seed: int | None = None, stochastic: bool = False
                ) -> tuple[Controller, dict]:
    """Controller and config of a run directory written by ``train.py``.

    ``seed`` selects one of the run's seeds (default: the best one by final evaluation reward,
    as recorded in ``summary.json``, else 0).
    """
    from jaxtraffic.checkpoint import load_run  # local import: checkpoint imports ppo

    run_dir = Path(run_dir)
    config, saved, summary = load_run(run_dir)
    if seed is None:
        seed = int(summary.get("best_seed", 0)) if summary else 0
    n_seeds = saved.obs_mean.shape[0]
    if not 0 <= seed < n_seeds:
        raise ValueError(f"seed {seed} not in run with {n_seeds} seeds")
    expected = 3 * int(config["n_points"]) + 3
    if saved.obs_mean.shape[-1] != expected or "gain_filter" not in config["env"]:
        raise ValueError(f"{run_dir} was written by an older jaxtraffic (observation of {saved.obs_mean.shape[-1]} "
                         f"values, expected {expected} with the applied gains): retrain it with train.py")
    ppo_cfg = config["ppo"]
    controller = policy_controller(
        jax.tree.map(lambda x: jnp.asarray(x[seed]), saved.params), saved.obs_mean[seed], saved.obs_var[seed],
        config["env"]["gain_max"], hidden=tuple(ppo_cfg["hidden"]), activation=ppo_cfg["activation"],
        init_sigma=ppo_cfg["init_sigma"], stochastic=stochastic, gain_filter=config["env"]["gain_filter"])
    return controller, config
