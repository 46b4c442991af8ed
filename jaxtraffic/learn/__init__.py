"""The learning algorithms a library user calls (imports ``model``, ``control``, ``sim``):

    env.py       the gymnax-style environment (``TrafficEnv``, ``EnvParams``)
    env_config.py  the environment's config as a user writes it (``EnvConfig``)
    ppo/         pure-JAX PPO: the algorithm (``make_train``, ``PPOConfig``) and its losses
    gradient/    gradient-based and CEM training of gain laws: settings, rollout objective, CEM

The run machinery above them (run directory, training loop, checkpoints, selection, ``load_policy``) is
``jaxtraffic.runs``. Submodules are imported explicitly (``from jaxtraffic.learn import ppo``)."""
