"""PPO's estimators and loss: Gaussian log-probability and entropy, generalised advantage estimation,
the clipped surrogate, and the loss of a minibatch (``Batch``). Pure functions of arrays."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = ["Batch", "clipped_surrogate", "compute_gae", "gaussian_entropy", "gaussian_log_prob", "ppo_loss"]


class Batch(NamedTuple):
    """What the PPO loss reads of a (mini)batch of transitions."""

    obs: Array
    action: Array
    logp: Array
    value: Array
    adv: Array  # GAE advantage
    target: Array  # value target


def gaussian_log_prob(x: Array, mean: Array, sigma: Array) -> Array:
    """log N(x; mean, diag(sigma^2)) summed over the last axis.

    Written out rather than taken from distrax (``MultivariateNormalDiag.log_prob``): two lines,
    checked against the closed form in numpy in tests/test_ppo.py, and distrax would be one more dependency pinned to
    jax releases for nothing else in the library."""
    z = (x - mean) / sigma
    return jnp.sum(-0.5 * z**2 - jnp.log(sigma) - 0.5 * jnp.log(2.0 * jnp.pi), axis=-1)


def gaussian_entropy(sigma: Array) -> Array:
    """Entropy of N(mean, diag(sigma^2)) summed over the last axis (nats); see ``gaussian_log_prob``."""
    return jnp.sum(0.5 + 0.5 * jnp.log(2.0 * jnp.pi) + jnp.log(sigma), axis=-1)


def compute_gae(rewards: Array, values: Array, dones: Array, last_value: Array, gamma, lam
                ) -> tuple[Array, Array]:
    """Generalised advantage estimates over a (T, ...) rollout.

    ``dones[t]`` marks that the episode ended after step t (so V(s_{t+1}) is not used); a
    truncated step must already carry the bootstrap gamma V(terminal obs) in ``rewards[t]``.
    Returns (advantages, value targets = advantages + values).

    Kept rather than taken from a library: it is a dozen tested lines, and it handles truncation
    correctly (the bootstrap of a truncated episode enters through the reward, while ``dones`` cuts
    the trace), where e.g. rejax's GAE treats a time-limit truncation like a termination.
    """
    def body(carry, xs):
        gae, next_value = carry
        r, v, d = xs
        nonterminal = 1.0 - d
        delta = r + gamma * next_value * nonterminal - v
        gae = delta + gamma * lam * nonterminal * gae
        return (gae, v), gae

    _, adv = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value),
                          (rewards, values, dones.astype(values.dtype)), reverse=True)
    return adv, adv + values


def clipped_surrogate(logp: Array, old_logp: Array, adv: Array, clip_eps) -> Array:
    """PPO-clip policy loss -E[min(ratio A, clip(ratio, 1-eps, 1+eps) A)]."""
    ratio = jnp.exp(logp - old_logp)
    return -jnp.mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * adv))


def ppo_loss(params, apply_fn, batch: Batch, ppo_config: Any):
    """(loss, statistics) of a minibatch: clipped surrogate, value loss and entropy bonus; ``ppo_config``: an
    ``algorithm.PPOConfig`` (its clip range and the value and entropy coefficients)."""
    mean, sigma, value = apply_fn(params, batch.obs)
    logp = gaussian_log_prob(batch.action, mean, sigma)
    adv = batch.adv
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg = clipped_surrogate(logp, batch.logp, adv, ppo_config.clip_eps)
    vf = 0.5 * jnp.mean((value - batch.target) ** 2)
    ent = jnp.mean(gaussian_entropy(sigma))
    loss = pg + ppo_config.vf_coef * vf - ppo_config.ent_coef * ent
    return loss, {"policy_loss": pg, "value_loss": vf, "entropy": ent,
                  "approx_kl": jnp.mean(batch.logp - logp), "sigma": jnp.mean(sigma)}
