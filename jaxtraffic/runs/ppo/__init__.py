"""PPO's run machinery: per-member views of a population (``members``), the validation suite and
best-checkpoint selection (``selection``), its hooks for the shared training loop (``trainer``), its saved policy
(``policy``) and export (``export``). The algorithm itself is ``jaxtraffic.learn.ppo``."""
