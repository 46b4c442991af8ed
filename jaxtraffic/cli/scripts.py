"""Console-script entry points (``[project.scripts]`` in pyproject.toml): ``jaxtraffic-train`` and
``jaxtraffic-evaluate``. The CLIs' ``main`` functions return their results (the run directory, the
metrics) for callers in Python; a console script's return value becomes the exit status, so these
return 0 instead."""

from __future__ import annotations


def train() -> int:
    from jaxtraffic.cli.train import main

    main()
    return 0


def evaluate() -> int:
    from jaxtraffic.cli.evaluate import main

    main()
    return 0
