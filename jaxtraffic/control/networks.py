"""Actor-critic networks (flax.linen) for the gain policy.

The actor maps the normalised observation to the mean of a diagonal Gaussian over the three
pre-squash actions; its scale is a learned, state-independent parameter of the network
(sigma = softplus(s) + ``sigma_offset``, the paper's 1e-6 offset). The paper's network outputs a
state-dependent scale too; in our runs a state-dependent scale collapsed within a few dozen
updates, so the standard PPO choice is used. The critic is a separate MLP.
Default: two hidden layers of 64 units (the paper's 8-layer network is ``hidden=(1024, 512, 512, 512, 512,
512, 512)``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import cast

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

SMALL_HIDDEN = (64, 64)

# what ActorCritic.apply returns: (mean, sigma, value)
ActorCriticApply = Callable[..., tuple[jax.Array, jax.Array, jax.Array]]


class MLP(nn.Module):
    hidden: Sequence[int]
    out: int
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.tanh(nn.Dense(width, kernel_init=nn.initializers.orthogonal(np.sqrt(2.0)))(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale))(x)


def actor_critic_size(d_in: int, hidden: Sequence[int], n_actions: int = 3) -> int:
    """The number of parameters of ``ActorCritic(hidden)`` on ``d_in`` inputs (counted, nothing built: the memory
    checks size a network before it is allocated)."""
    def mlp(out: int) -> int:
        widths = [d_in, *hidden, out]
        return sum(a * b + b for a, b in zip(widths[:-1], widths[1:], strict=True))

    return mlp(n_actions) + n_actions + mlp(1)


class ActorCritic(nn.Module):
    """Returns (mean (..., 3), sigma (..., 3), value (...,))."""

    hidden: Sequence[int] = SMALL_HIDDEN
    n_actions: int = 3
    init_sigma: float = 0.5
    sigma_offset: float = 1e-6

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        mean = MLP(self.hidden, self.n_actions, out_scale=0.01, name="actor")(x)
        bias = np.log(np.expm1(self.init_sigma))  # softplus^{-1}(init_sigma)
        raw_sigma = self.param("sigma", nn.initializers.constant(bias), (self.n_actions,))
        sigma = jnp.broadcast_to(nn.softplus(raw_sigma) + self.sigma_offset, mean.shape)
        value = MLP(self.hidden, 1, out_scale=1.0, name="critic")(x)[..., 0]
        return mean, sigma, value


def actor_critic_apply(network: ActorCritic) -> ActorCriticApply:
    """``network.apply`` itself, typed as returning what ``ActorCritic.__call__`` returns: flax types
    ``Module.apply`` as ``Any | tuple[Any, variables]``, the second form being for ``mutable=``, never passed here."""
    return cast(ActorCriticApply, network.apply)
