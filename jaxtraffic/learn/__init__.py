"""The learning layer (imports ``model``, ``control``, ``sim``): the gymnax-style environment,
PPO, the training loop, checkpoints and ``load_policy``, the learning curve. Submodules are
imported explicitly (``from jaxtraffic.learn import ppo``)."""
