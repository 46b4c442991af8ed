"""The learning layer (imports ``model``, ``control``, ``sim``), by concern:

    env.py       the gymnax-style environment
    config/      the config tree (``TrainConfig``) and its checks
    runs/        what every run shares: checkpoints, run directory and signals, learning curve, TensorBoard, and
                 the one host training loop (``runs.loop.run_training``)
    ppo/         PPO: the algorithm, its losses, members, validation and selection, its trainer, its policy
    gradient/    gradient-based and CEM training: settings, objective, CEM, its trainer, its policy
    policy.py    ``load_policy``: a trained run's controller, whatever the algorithm

Submodules are imported explicitly (``from jaxtraffic.learn.ppo import trainer``)."""

from jaxtraffic.learn.policy import load_policy

__all__ = ["load_policy"]
