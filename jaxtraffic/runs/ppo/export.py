"""A trained PPO run's policy as a plain function, for use outside jaxtraffic's rollouts.

``load_predict(run_dir)`` returns ``predict(obs) -> a``: the deterministic action of the run's policy
for the gain environment's observation (shape (F,) or a batch (B, F), float32), as normalised gains
a = tanh(mean) in [-1, 1]^3, the action of the Gymnasium environment (``jaxtraffic.ecosystem``); the
target gains are gain_max * a. It is the inverse bridge of ``ecosystem.policy_as_controller``: a run's
``predict`` made back into a controller acts like ``load_policy(run_dir)`` (to float rounding).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraffic.control.gain_policy import normalize_obs
from jaxtraffic.control.networks import ActorCritic, actor_critic_apply
from jaxtraffic.runs.policy import load_policy

__all__ = ["load_predict"]


def load_predict(run_dir: str | Path, seed: int | None = None, checkpoint: str = "best"
                 ) -> Callable[[np.ndarray], np.ndarray]:
    """``predict(obs) -> a`` (numpy in, numpy out, jit-compiled) of a PPO run directory (``seed`` and
    ``checkpoint`` as for ``load_policy``). A gradient-trained run has no policy of the environment's
    observation (its law is fixed gains, a delay schedule or its own network): ``ValueError``."""
    controller, config = load_policy(run_dir, seed, checkpoint)
    if config.run.algo != "ppo":
        raise ValueError(f"{run_dir}: a gradient-trained run ({config.grad.policy}) has no predict(obs) of the "
                         "environment's observation; load_policy gives its controller")
    s = controller.settings
    network = ActorCritic(hidden=tuple(config.ppo.hidden), init_sigma=config.ppo.init_sigma)
    size = s.obs_mean.shape[-1]

    @jax.jit
    def action(obs):
        mean, _, _ = actor_critic_apply(network)(s.params, normalize_obs(obs, s.obs_mean, s.obs_var))
        return jnp.tanh(mean)

    def predict(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.shape[-1:] != (size,):
            raise ValueError(f"observation of shape {obs.shape}: this policy sees {size} values (the environment "
                             f"of {run_dir}: n_points {config.plant.n_points}, obs_segments {config.env.obs_segments})")
        return np.asarray(action(obs))

    return predict
