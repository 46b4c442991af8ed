#!/usr/bin/env python
"""Train the paper's PPO gain policy: ``python train.py [flags]`` (``--help`` lists them).

A thin wrapper around ``jaxtraffic.cli.train.main``.
"""

from jaxtraffic.cli.train import build_parser, main, settings_from_args

__all__ = ["build_parser", "main", "settings_from_args"]

if __name__ == "__main__":
    main()
