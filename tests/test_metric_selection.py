"""Metrics chosen by the caller (``simulate(..., metrics=...)``, issue 48.1): a selection returns exactly the
metrics it names, each equal bit for bit to the default call's, and only the running sums they read are carried."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from conftest import SMALL

from jaxtraffic import TrafficParams, backstepping, lyapunov, simulate, simulate_batch, stack_params
from jaxtraffic.learn.gradient.objective import OBJECTIVE_METRICS
from jaxtraffic.paper.scenarios import ROBUST_METRICS
from jaxtraffic.runs.ppo.selection import SUITE_METRICS
from jaxtraffic.sim import metrics as sim_metrics

P = TrafficParams(**SMALL, alpha_noise=0.1)
STEPS = 120
# what the library's own callers ask for, then some of the others
SELECTIONS = (ROBUST_METRICS, SUITE_METRICS, OBJECTIVE_METRICS, ("diverged",), ("J_TTT", "control_effort", "max_cfl"),
              ("J_comfort", "J_comfort_at2", "time_to_reward_target_s"), ("J_comfort_switch_on_kmh",), ())


CHILD = """
import json, sys
import jax, numpy as np
from jaxtraffic import TrafficParams, backstepping, lyapunov, simulate
from jaxtraffic.learn.gradient.objective import OBJECTIVE_METRICS
from jaxtraffic.paper.scenarios import ROBUST_METRICS
from jaxtraffic.runs.ppo.selection import SUITE_METRICS
p = TrafficParams(n_points=41, dt=0.5, alpha_noise=0.1)
bad = []
for name, c in {"open": None, "lyap": lyapunov(), "bs": backstepping(float(p.delay))}.items():
    full = simulate(p, c, n_steps=120, key=jax.random.PRNGKey(5))
    for names in (ROBUST_METRICS, SUITE_METRICS, OBJECTIVE_METRICS, ("J_TTT", "control_effort", "max_cfl"), ()):
        res = simulate(p, c, n_steps=120, key=jax.random.PRNGKey(5), metrics=names)
        bad += [[name, k] for k in names if not np.array_equal(res.metrics[k], full.metrics[k], equal_nan=True)]
        bad += [[name, "final"] for x, y in zip(jax.tree.leaves(res.final), jax.tree.leaves(full.final))
                if not np.array_equal(x, y, equal_nan=True)]
print(json.dumps(bad))
"""


def test_the_callers_selections_are_bit_identical_with_the_library_flags():
    """With the XLA flags a user's program has (not the test suite's cheaper ones, under which two programs may
    differ by an ulp, tests/xla_flags.py), the callers' selections keep the default call's values bit for bit."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


@pytest.mark.parametrize("controller", [None, lyapunov(), backstepping(float(P.delay))], ids=["open", "lyap", "bs"])
def test_each_selection_keeps_the_default_values(controller):
    """Every selection returns exactly its metrics; under the test suite's XLA flags two programs may differ by
    an ulp (tests/xla_flags.py), so floats are compared to float32 rounding here, flags and codes exactly."""
    key = jax.random.PRNGKey(5)
    full = simulate(P, controller, n_steps=STEPS, key=key)
    assert set(full.metrics) == set(sim_metrics.METRIC_NAMES)
    for names in SELECTIONS + tuple((k,) for k in sim_metrics.METRIC_NAMES):
        res = simulate(P, controller, n_steps=STEPS, key=key, metrics=names)
        assert set(res.metrics) == set(names), names
        for k in names:
            _close(res.metrics[k], full.metrics[k], (names, k))
        for x, y in zip(jax.tree.leaves((res.final, res.controller_state)),
                        jax.tree.leaves((full.final, full.controller_state)), strict=True):
            _close(x, y, names)


def _close(x, y, what) -> None:
    x, y = np.asarray(x), np.asarray(y)
    if np.issubdtype(x.dtype, np.floating):
        np.testing.assert_allclose(x, y, rtol=4e-6, atol=0, err_msg=str(what))
    else:
        assert np.array_equal(x, y), what


def test_batched_selection_and_any_iterable():
    params = stack_params(*[P.replace(delay=d, alpha=a) for d, a in [(0.0, 0.5), (2.0, 0.7), (4.0, 0.9)]])
    full = simulate_batch(params, lyapunov(), n_steps=STEPS, nominal=P)
    for names in (frozenset(ROBUST_METRICS), list(SUITE_METRICS)):
        res = simulate_batch(params, lyapunov(), n_steps=STEPS, nominal=P, metrics=names)
        assert set(res.metrics) == set(names)
        for k in names:
            _close(res.metrics[k], full.metrics[k], k)
    one = simulate(P, None, n_steps=4, metrics="final_reward")  # a string: that one metric
    assert set(one.metrics) == {"final_reward"}


def test_only_the_sums_read_are_carried():
    assert sim_metrics.accumulators(ROBUST_METRICS) == frozenset()  # final-state metrics: no running sums
    assert sim_metrics.accumulators(("J_comfort",)) == {"J_comfort", "a_prev"}
    assert sim_metrics.accumulators(("J_comfort_no_switch_on_kmh",)) == {
        "J_comfort_a2", "J_comfort_at2", "J_comfort_switch", "a_prev"}
    acc = sim_metrics.init_metrics(5, keep=sim_metrics.accumulators(("control_effort",)))
    assert {k for k, v in vars(acc).items() if v is not None} == {"effort_sq", "n_active"}
    assert sim_metrics.accumulators(sim_metrics.METRIC_ACCUMULATORS) == set(vars(sim_metrics.init_metrics(5)))


def test_unknown_metric_names_the_valid_ones():
    with pytest.raises(ValueError, match=r"unknown metric\(s\) \['J_tt'\].*J_TTT, J_fuel"):
        simulate(P, None, n_steps=4, metrics=("J_tt", "J_TTT"))
    with pytest.raises(ValueError, match="unknown metric"):
        simulate_batch(stack_params(P, P), None, n_steps=4, metrics=["final_L2"])
