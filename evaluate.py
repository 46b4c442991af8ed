#!/usr/bin/env python
"""Reproduce the paper's section 4: ``python evaluate.py [--run RUN_DIR] [--out results/]``.

A thin wrapper around ``jaxtraffic.cli.evaluate.main`` (``--help`` lists the flags).
"""

import os
import signal

# Ctrl-C while jax loads (about 1.5 s; nothing to save yet): exit 130 at once, without a traceback
signal.signal(signal.SIGINT, lambda signum, frame: os._exit(128 + signum))
from jaxtraffic.cli.evaluate import main, parse_args  # noqa: E402

signal.signal(signal.SIGINT, signal.default_int_handler)

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    main()
