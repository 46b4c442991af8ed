"""A controller brought in by ``evaluate.py --controller`` in the end-to-end test: a trained run's policy as a
plain ``predict(obs)`` (``learn.ppo.export.load_predict``), made a controller through the bridge a policy trained
elsewhere takes (``ecosystem.policy_as_controller``), on the run's grid. It must score as the run itself."""

from __future__ import annotations

from jaxtraffic.ecosystem import policy_as_controller
from jaxtraffic.runs.policy import load_policy, policy_grid
from jaxtraffic.runs.ppo.export import load_predict
from jaxtraffic.runs.ppo.trainer import build


def predict_controller(run_dir: str):
    _, config = load_policy(run_dir)
    controller = policy_as_controller(load_predict(run_dir), build(config)[1], batched=True, name="ppo_predict")
    return controller, policy_grid(config)
