"""The indices' units (``sim.units``): what they say is what the code computes, and the tables print them."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxtraffic as jt
from jaxtraffic.paper.summaries import UNITS
from jaxtraffic.sim.units import INDEX_UNITS, labelled


def test_j_ttt_over_1000_is_the_total_travel_time_in_vehicle_seconds():
    """A uniform equilibrium held for T seconds on a road of L metres has rho L T vehicle-seconds of travel time
    (rho in veh/m): J_TTT, in veh/km·m·s, is 1000 times that."""
    p = jt.TrafficParams(n_points=21)
    rho_bar, v_bar = (float(x) for x in jt.equilibrium(p))
    n_steps = 50
    res = jt.simulate(p, n_steps=n_steps, rho0=jnp.full(21, rho_bar), v0=jnp.full(21, v_bar))
    veh_s = rho_bar * p.L * n_steps * p.dt
    np.testing.assert_allclose(float(res.metrics["J_TTT"]) / 1000.0, veh_s, rtol=1e-4)


def test_every_index_is_printed_with_its_unit():
    assert labelled("J_TTT") == "J_TTT (veh/km·m·s)"
    assert all(labelled(k).endswith(f"({u})") for k, u in INDEX_UNITS.items())
    # metrics.json's units say the same (it once said veh*s for J_TTT: 1000x off)
    assert UNITS["J_TTT"].startswith(INDEX_UNITS["J_TTT"])
