"""A hand-written law brought in by ``evaluate.py --judge --controller`` in test_judge.py."""

from __future__ import annotations

from jaxtraffic.control import lyapunov


def soft_lyapunov():
    return lyapunov(0.5)


SEEN = []


def normalised_model(path: str):
    """A bridge of a model file ``path``: records the statistics ``evaluate.py --controller-normalization`` set."""
    from jaxtraffic.ecosystem.normalization import active

    SEEN.append(active())
    return lyapunov(0.5)


def network_51():
    """A network built for 51 points (the observation of 3 x 51 + 3 features), returned without its grid: it cannot
    act on another grid (``evaluate.py`` must refuse it, naming it, before any work)."""
    import jax.numpy as jnp

    from jaxtraffic.ecosystem import policy_as_controller

    weights = jnp.full((3, 3 * 51 + 3), 1e-3)
    return policy_as_controller(lambda obs: jnp.tanh(weights @ obs), n_points=51, obs_segments=0, host=False)


def network_51_on_its_grid():
    """The same network with the grid it was built for: adapted to any plant that refines it."""
    from jaxtraffic.ecosystem import controller_grid

    return network_51(), controller_grid(n_points=51, obs_segments=0)


def exits():
    """A function that calls ``sys.exit(0)``: a failure of the controller, never a clean exit of evaluate.py."""
    import sys

    sys.exit(0)


def raises_when_traced():
    """A controller whose own code raises while it is traced."""
    from jaxtraffic.control import Controller

    def act(settings, state, obs, nominal, key):
        raise RuntimeError("my controller is broken")

    return Controller(settings=(), act_fn=act, name="broken")


CALLS = []


def raises_on_the_second_call():
    """A host policy that answers its first call (the up-front check) and raises from the second on, as a policy
    that fails during the run."""
    import numpy as np

    from jaxtraffic.ecosystem import policy_as_controller

    def policy(obs):
        CALLS.append(1)
        if len(CALLS) > 1:
            raise RuntimeError("my policy failed at step 2")
        return np.zeros(3, np.float32)

    return policy_as_controller(policy, n_points=11, obs_segments=0)
