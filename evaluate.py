#!/usr/bin/env python
"""Reproduce the paper's section 4: ``python evaluate.py [--run RUN_DIR] [--out results/]``.

A thin wrapper around ``jaxtraffic.cli.evaluate.main`` (``--help`` lists the flags).
"""

from jaxtraffic.cli.evaluate import main, parse_args

__all__ = ["main", "parse_args"]

if __name__ == "__main__":
    main()
