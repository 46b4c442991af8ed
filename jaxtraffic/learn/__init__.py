"""The learning layer (imports ``model``, ``control``, ``sim``): the gymnax-style environment,
PPO, the validation suite, the training loop, checkpoints and ``load_policy``, the learning curve. Other submodules
are imported explicitly (``from jaxtraffic.learn import ppo``)."""

from jaxtraffic.learn.policy import load_policy

__all__ = ["load_policy"]
