"""The validation suite of PPO checkpoints (jaxtraffic/runs/ppo/selection.py), tiny grid."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraffic.control.baselines import backstepping, open_loop
from jaxtraffic.model.params import TrafficParams
from jaxtraffic.runs.ppo.selection import BAD, make_suite

TP = TrafficParams(n_points=21, delay=0.5)


@pytest.mark.slow
def test_validation_score_of_the_reference_and_of_the_open_loop():
    """``make_suite``: backstepping scored against itself gives exactly 1 (its L2 ratio is 1, its
    J_comfort ratio 1 / 1.2); the open loop, which does not converge, is rejected (BAD)."""
    suite = make_suite(TP, 600, (0.3, 0.5, 0.8))
    assert len(suite.reference["labels"]) == 6
    members = jax.tree.map(lambda *x: jnp.stack(x), backstepping(0.5), backstepping(0.5))
    out = suite(members, 2)
    assert out["ratio"].shape == (2, 6)
    np.testing.assert_allclose(out["score"], 1.0, rtol=1e-5)
    np.testing.assert_array_equal(out["ratio"][:, [0, 2, 3, 5]], 0.0)  # off-nominal delays: stability only
    ol = jax.tree.map(lambda x: jnp.asarray(x)[None], open_loop())
    assert suite(ol, 1)["score"][0] == BAD
