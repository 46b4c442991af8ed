"""A trained run's policy as a plain ``predict(obs)`` (``learn.ppo.export.load_predict``), and back through
``ecosystem.policy_as_controller``: the two bridges round-trip. Reads the suite's tiny training session
(``tiny_runs.py``), late in the order so that it has been written by then."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxtraffic import simulate
from jaxtraffic.control.gain_policy import feature_size
from jaxtraffic.ecosystem import controller_grid, policy_as_controller
from jaxtraffic.runs.policy import load_policy, policy_grid
from jaxtraffic.runs.ppo.export import load_predict
from jaxtraffic.runs.ppo.trainer import build


def test_predict_of_a_run_made_back_into_a_controller_acts_like_the_run(tiny_run_a):
    """``load_predict`` (our policy as a plain function) through ``policy_as_controller`` (a function as a
    controller) is the run's own controller, to float rounding, on a plant other than its training one."""
    ctrl, config = load_policy(tiny_run_a)
    predict = load_predict(tiny_run_a)
    env_params = build(config)[1]
    obs = np.zeros((5, feature_size(config.plant.n_points, config.env.obs_segments)), np.float32)
    a = predict(obs)
    assert a.shape == (5, 3) and np.all(np.abs(a) <= 1) and predict(obs[0]).shape == (3,)
    with pytest.raises(ValueError, match="sees"):
        predict(np.zeros(4, np.float32))
    bridged = policy_as_controller(predict, env_params, batched=True)
    assert controller_grid(env_params) == policy_grid(config)
    plant = env_params.traffic.replace(delay=1.0, alpha=0.3)
    got, want = (simulate(plant, c, n_steps=30).metrics for c in (bridged, ctrl))
    for k in ("J_comfort", "final_rho_L2", "final_v_L2", "final_reward"):
        np.testing.assert_allclose(float(got[k]), float(want[k]), rtol=2e-4, atol=1e-7, err_msg=k)


def test_a_gradient_run_has_no_predict(tiny_runs_root):
    from tiny_runs import GRADIENT_ROOT

    with pytest.raises(ValueError, match="no predict"):
        load_predict(tiny_runs_root / GRADIENT_ROOT / "gradient-gains")


def test_an_exported_gradient_run_loads_the_same_policy_without_its_optimiser_state(tiny_runs_root, tmp_path, capsys):
    """``evaluate.py``'s export of a gradient-trained run (``export_runs``) writes its checkpoint without the
    Adam state: smaller, the same policy through ``load_policy``, and a resume of it is refused in one line."""
    from tiny_runs import GRADIENT_ROOT

    from jaxtraffic.cli import evaluate as evaluate_cli
    from jaxtraffic.cli import train as train_cli
    from jaxtraffic.runs import checkpoint as ckpt

    src = tiny_runs_root / GRADIENT_ROOT / "gradient-gains"
    evaluate_cli.export_runs({"grad_gains": {"run_dir": str(src)}}, tmp_path)
    out = tmp_path / "grad_gains"
    runner, meta = ckpt.load_checkpoint(out)
    full, _ = ckpt.load_checkpoint(src)
    assert "opt_state" in full and "opt_state" not in runner and meta[ckpt.POLICY_ONLY] is True
    assert (out / ckpt.CHECKPOINT).stat().st_size < (src / ckpt.CHECKPOINT).stat().st_size
    (want, _), (got, _) = load_policy(src), load_policy(out)
    for a, b in zip(jax.tree.leaves(want.settings), jax.tree.leaves(got.settings), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(SystemExit) as exc:
        train_cli.main(["--out-dir", str(out), "--resume", "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "cannot be resumed" in err and "Traceback" not in err, err
