"""A complete minimal policy for ``evaluate.py --controller`` (docs/tutorials/own-policy.md):

    python evaluate.py --judge --controller mine=examples/my_policy.py:controller --out results/mine

``controller()`` returns the policy and the grid it was built for; evaluate.py adapts it to each plant whose
grid refines that one ((n_plant - 1) a multiple of N_POINTS - 1; the paper plant's 201 points and the
reference plant's 801 both are) and refuses it, naming it, before any work on a plant that does not.
"""

import jax.numpy as jnp

from jaxtraffic.control import Controller
from jaxtraffic.control.adapter import ControllerGrid

N_POINTS = 11  # the nodes of the grid the policy was built for (here: one node every 200 m)
GAIN = 0.5  # s: the time gap added per unit of relative density deviation


def act(settings, state, obs, nominal, key):
    """The time gap h (s) at each of the policy's nodes: h_bar, lengthened where the road is denser than
    its mean (obs.rho in veh/m at the N_POINTS nodes; obs.v in m/s; nominal: the model's parameters)."""
    deviation = (obs.rho - jnp.mean(obs.rho)) / jnp.mean(obs.rho)
    return nominal.h_bar + settings * deviation, state


def controller():
    return Controller(settings=jnp.asarray(GAIN), act_fn=act, name="my_policy"), ControllerGrid(n_points=N_POINTS)
