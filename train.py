#!/usr/bin/env python
"""Train a gain policy: ``python train.py [ppo|gradient] [flags]`` (``--help`` lists them).

A thin wrapper around ``jaxtraffic.cli.train.main``.
"""

import os
import signal

# Ctrl-C while jax loads (about 1.5 s; nothing to save yet): exit 130 at once, without a traceback
signal.signal(signal.SIGINT, lambda signum, frame: os._exit(128 + signum))
from jaxtraffic.cli.train import config_from_args, main  # noqa: E402

signal.signal(signal.SIGINT, signal.default_int_handler)

__all__ = ["main", "config_from_args"]

if __name__ == "__main__":
    main()
