"""A hyperparameter's allowed range lives in its own field's metadata (``hyper``), checked there (``check_fields``).

``lr: float = hyper(1e-3, lo=0.0, lo_open=True)`` declares the field, its default and its range once, in the
dataclass that uses it (``model.params.TrafficParams``, ``learn.env.EnvParams``, ``learn.ppo.PPOConfig``,
``learn.gradient.config.GradientConfig``); the run's config and the struct itself both check it against that metadata,
with one message naming the field, e.g. ``gamma = 5.0: must lie in (0.0, 1.0]``. A field's ``help`` (one line)
is its flag's help text on the command line. This module imports nothing from jaxtraffic (the ground floor).
"""

from __future__ import annotations

import dataclasses
from typing import Any

Range = tuple[float | None, bool, float | None, bool]  # (lo, lo inclusive, hi, hi inclusive); None: unbounded


def hyper(default: Any, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
          hi_open: bool = False, static: bool = False, **meta: Any) -> Any:
    """A dataclass field with ``default`` and its range ``lo`` .. ``hi`` (inclusive unless ``*_open``) in its
    metadata; ``static``: not a pytree leaf of a ``flax.struct`` dataclass (a shape or a count)."""
    bounded = lo is not None or hi is not None
    metadata = {**({"range": (lo, not lo_open, hi, not hi_open)} if bounded else {}), **meta}
    if static:
        metadata["pytree_node"] = False
    return dataclasses.field(default=default, metadata=metadata)


def range_of(cls: Any, name: str) -> Range | None:
    """The range of the field ``name`` of the dataclass ``cls`` (``None``: no range)."""
    return next((f.metadata.get("range") for f in dataclasses.fields(cls) if f.name == name), None)


def fail(name: str, value: Any, why: str) -> ValueError:
    """The error of a bad value: ``name = value: why``."""
    return ValueError(f"{name} = {value!r}: {why}")


def range_text(rule: Range) -> str:
    lo, lo_in, hi, hi_in = rule
    if hi is None:
        return f"must be {'>=' if lo_in else '>'} {lo}"
    return f"must lie in {'[' if lo_in else '('}{lo}, {hi}{']' if hi_in else ')'}"


def in_range(value: Any, rule: Range) -> bool:
    lo, lo_in, hi, hi_in = rule
    ok = (value >= lo if lo_in else value > lo) if lo is not None else True
    return bool(ok and ((value <= hi if hi_in else value < hi) if hi is not None else True))


def check_value(name: str, value: Any, rule: Range | None) -> None:
    """``fail`` unless ``value`` (each element of a tuple or list) obeys ``rule``; no rule, or ``None``, passes."""
    if rule is None or value is None:
        return
    for x in value if isinstance(value, (tuple, list)) else (value,):
        if not in_range(x, rule):
            raise fail(name, x, range_text(rule))


def check_fields(struct: Any, skip: tuple[str, ...] = ()) -> None:
    """``check_value`` of every field of the dataclass ``struct`` that has a range (but those in ``skip``)."""
    for f in dataclasses.fields(struct):
        if f.name not in skip:
            check_value(f.name, getattr(struct, f.name), f.metadata.get("range"))
