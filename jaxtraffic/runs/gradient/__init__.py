"""The gradient trainer's run machinery: its hooks for the shared training loop (``trainer``) and its saved
policy (``policy``). The objective and CEM are ``jaxtraffic.learn.gradient``."""
