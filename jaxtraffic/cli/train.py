"""Train the paper's PPO gain policy: ``python train.py [flags]`` (``--help`` lists them).

A default run trains the D = 4 s policy and writes, in ``--out-dir`` (default runs/default):
config.json, checkpoint.msgpack, learning_curve.csv/.png and summary.json. Ctrl-C saves a
checkpoint; ``--resume`` continues from it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

from jaxtraffic.learn.config import SECTIONS, TrainConfig
from jaxtraffic.learn.trainer import train


def _pair(kind):
    def parse(text: str):
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected LO,HI, got {text!r}")
        return tuple(kind(p) for p in parts)
    return parse


GROUPS = {"run": "run", "plant": "plant and grid", "env": "episodes and domain randomisation", "algo": "PPO"}
_PARSERS = {"int": int, "float": float, "str": str, "float | None": float,
            "tuple[float, float]": _pair(float), "tuple[float, float] | None": _pair(float),
            "tuple[int, int]": _pair(int)}


def build_parser() -> argparse.ArgumentParser:
    """One flag per leaf of ``TrainConfig`` (``--n-points`` for ``plant.n_points``), with the field's
    default and help: the flags cannot drift from the library's defaults."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for section in ("run", "plant", "env", "algo"):
        g = p.add_argument_group(GROUPS[section])
        for f in dataclasses.fields(SECTIONS[section]):
            flag = "--" + f.name.replace("_", "-")
            if f.type == "bool":
                g.add_argument(flag, action="store_true", help=f.metadata["help"])
                continue
            g.add_argument(flag, type=_PARSERS[f.type], default=f.default, choices=f.metadata.get("choices"),
                           help=f.metadata["help"])
    return p


def settings_from_args(argv: list[str] | None = None) -> TrainConfig:
    args = build_parser().parse_args(argv)
    if args.min_wave_speed == -math.inf:  # the paper's rule alone (stored as null in the JSON outputs)
        args.min_wave_speed = None
    return TrainConfig.from_flat(**vars(args))


def main(argv: list[str] | None = None) -> Path:
    """Parse flags, train, return the run directory."""
    try:
        settings = settings_from_args(argv)
        return train(settings)
    except ValueError as err:  # invalid parameters: a clear message, no traceback
        print(f"train.py: error: {err}", file=sys.stderr)
        raise SystemExit(2) from err

