"""A hand-written law brought in by ``evaluate.py --judge --controller`` in test_judge.py."""

from __future__ import annotations

from jaxtraffic.control import lyapunov


def soft_lyapunov():
    return lyapunov(0.5)


SEEN = []


def normalised_model(path: str):
    """A bridge of a model file ``path``: records the statistics ``evaluate.py --controller-normalization`` set."""
    from jaxtraffic.ecosystem.normalization import active

    SEEN.append(active())
    return lyapunov(0.5)
