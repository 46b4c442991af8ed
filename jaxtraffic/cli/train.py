"""Train a gain policy: PPO (the paper's) or by gradient through the simulator (``--algo gradient``).

``python train.py [flags]`` (``--help`` lists them).

A default run trains the D = 4 s policy and writes, in ``--out-dir`` (default runs/default):
config.json, checkpoint.msgpack, learning_curve.csv/.png and summary.json. Ctrl-C or SIGTERM stops
after the current chunk with its checkpoint saved (exit 130 / 143); ``--resume`` continues from it.
The same command runs as N cooperating processes (PPO and ``--algo gradient``) with
``--coordinator-address HOST:PORT --num-processes N --process-id I`` or the ``JAX_*`` variables
(``jaxtraffic.platform.distributed``; docs/tutorials/cluster.md).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from jaxtraffic.cli import errors
from jaxtraffic.cli.options import program
from jaxtraffic.platform import compile_cache, distributed
from jaxtraffic.runs.config import RUN_CONTROL, RunConfig, TrainConfig, check_flags_apply, load_config
from jaxtraffic.runs.config.toml import read_flat
from jaxtraffic.runs.config.tree import leaf_fields
from jaxtraffic.runs.gradient.trainer import train_gradient
from jaxtraffic.runs.ppo.trainer import train
from jaxtraffic.runs.session import TrainingInterrupted, check_resumable


def _pair(kind):
    def parse(text: str):
        parts = text.split(",")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"expected LO,HI, got {text!r}")
        return tuple(kind(p) for p in parts)
    return parse


def _many(kind):
    def parse(text: str):
        try:
            return tuple(kind(p) for p in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated values, got {text!r}") from None
    return parse


def _gain_bounds(text: str):
    """One bound for every gain, or one per gain: ETA1,ETA2,ETA3."""
    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or ETA1,ETA2,ETA3, got {text!r}") from None
    if len(parts) not in (1, 3):
        raise argparse.ArgumentTypeError(f"expected one bound or three (ETA1,ETA2,ETA3), got {text!r}")
    return parts[0] if len(parts) == 1 else tuple(parts)


PROG = program("train.py")  # in messages: the program the user typed
# flags of the last release that are gone: what to give instead
REMOVED = {"--network": "--hidden (layer sizes, e.g. 64,64)", "--lr-decay-steps": "--lr (the rate is constant)",
           "--lr-final": "--lr (the rate is constant)", "--certificate-weight": "nothing (the penalty is gone)",
           "--effort-weight": "nothing (the term is gone)"}
GROUPS = {"run": "run", "plant": "plant and grid", "env": "episodes and domain randomisation", "ppo": "PPO",
          "grad": "gradient-based training (--algo gradient)"}
_PARSERS = {"int": int, "float": float, "str": str, "float | None": float, "int | None": int, "str | None": str,
            "tuple[float, float]": _pair(float), "tuple[float, float] | None": _pair(float),
            "tuple[int, int]": _pair(int), "tuple[float, ...]": _many(float), "tuple[float, ...] | None": _many(float),
            "tuple[int, ...]": _many(int), "tuple": _many(int),
            "tuple[float, float, float]": _many(float), "float | tuple[float, float, float]": _gain_bounds}


def build_parser() -> argparse.ArgumentParser:
    """One flag per leaf of ``TrainConfig`` (``--n-points`` for ``plant.n_points``), with the field's
    default and help: the flags cannot drift from the library's defaults."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__, allow_abbrev=False,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument("--config", default=None, metavar="FILE.toml",
                        help="start from this config file (a run's config.toml); flags given override it")
    for section in ("run", "plant", "env", "ppo", "grad"):
        g = parser.add_argument_group(GROUPS[section])
        defaults = getattr(TrainConfig(), section)
        for f in leaf_fields(section):
            flag = ["--" + f.name.replace("_", "-"), *(["--seeds"] if f.name == "num_seeds" else [])]
            default = None if section == "grad" else getattr(defaults, f.name)  # grad: the policy's default
            if f.type == "bool":  # on by default: --no-FLAG turns it off
                action = argparse.BooleanOptionalAction if default else "store_true"
                g.add_argument(*flag, action=action, default=default, help=f.metadata["help"])
                continue
            default = None if f.name == "out_dir" else default  # resolved from --algo below
            g.add_argument(*flag, type=_PARSERS[f.type], default=default, choices=f.metadata.get("choices"),
                           help=f.metadata["help"])
    distributed.add_flags(parser)
    return parser


def _version() -> str:
    """The package's version as written in ``jaxtraffic._version`` (an editable install's metadata can be stale)."""
    from jaxtraffic._version import __version__

    return __version__


def config_from_args(argv: list[str] | None = None) -> TrainConfig:
    """The training configuration the flags ``argv`` (default: the command line's) describe."""
    return _config(build_parser().parse_args(argv), argv)


def _config(args: argparse.Namespace, argv: list[str] | None) -> TrainConfig:
    """The training configuration of parsed flags: the cluster flags dropped, --out-dir's default resolved;
    with --config, that file's fields under the flags given."""
    if args.config is not None:
        given = explicit_flags(argv)
        base = {"out_dir": None, **read_flat(args.config)}
        args = argparse.Namespace(**{**vars(args), **{k: v for k, v in base.items() if k not in given}})
    args = argparse.Namespace(**{k: v for k, v in vars(args).items() if k not in (*distributed.FLAGS, "config")})
    if args.min_wave_speed == -math.inf:  # the paper's rule alone (stored as null in the JSON outputs)
        args.min_wave_speed = None
    if args.out_dir is None:
        args.out_dir = f"runs/gradient-{args.policy}" if args.algo == "gradient" else RunConfig.out_dir
    grad = {f.name for f in leaf_fields("grad")}
    return TrainConfig.from_flat(**{k: v for k, v in vars(args).items() if k not in grad or v is not None})


def explicit_flags(argv: list[str] | None = None) -> dict:
    """The flags given on the command line (not their defaults), by field name."""
    p = build_parser()
    for action in p._actions:
        action.default = argparse.SUPPRESS
    return vars(p.parse_args(argv))


def resumed_config(config: TrainConfig, given: dict) -> TrainConfig:
    """On --resume: the run's saved configuration, with the run-control flags given on the command line
    (``config.RUN_CONTROL``; for the gradient trainer also --grad-steps) applied, and recorded in the
    run's config.json; a flag that would change the trained problem is an error."""
    saved = load_config(config.run.out_dir)
    control = (*RUN_CONTROL, "grad_steps") if saved.run.algo == "gradient" else RUN_CONTROL
    flat, old = config.flat(), saved.flat()
    changed = [f"--{k.replace('_', '-')} {flat[k]!r} (the run's value: {old[k]!r})" for k in given
               if k not in control and k in old and flat[k] != old[k]]
    if changed:
        raise ValueError("--resume continues the run with its saved configuration; these flags would change it: "
                         + ", ".join(changed) + "; drop them, or start a new run (--overwrite clears this one)")
    return saved.replace(**{**{k: flat[k] for k in given if k in control}, "resume": True,
                            "out_dir": config.run.out_dir})


def main(argv: list[str] | None = None) -> Path:
    """Parse flags, start ``jax.distributed`` if asked (``jaxtraffic.platform.distributed``: before anything
    runs on a device), train, return the run directory. Exit status 2 for invalid flags or a broken
    run directory, 74 for an OS error (``cli.errors``), 130 / 143 after SIGINT / SIGTERM (``runs.ppo.trainer``)."""
    try:
        gone = [a.split("=")[0] for a in (sys.argv[1:] if argv is None else argv) if a.split("=")[0] in REMOVED]
        if gone:
            raise ValueError(f"{gone[0]} was removed; use {REMOVED[gone[0]]}")
        args = build_parser().parse_args(argv)
        config = _config(args, argv)
        cluster = [getattr(args, k) for k in distributed.FLAGS]
        distributed.initialize(*cluster)
        compile_cache.enable()  # before the first compilation (jaxtraffic.platform.compile_cache)
        given = {k: v for k, v in explicit_flags(argv).items() if k != "config"}
        if config.run.resume:
            check_resumable(Path(config.run.out_dir))
            config = resumed_config(config, given)
        check_flags_apply(config.run.algo, given)  # (on resume: the run's algorithm)
        return train_gradient(config) if config.run.algo == "gradient" else train(config)
    except TrainingInterrupted as exc:  # the trainer has said what is saved
        raise SystemExit(exc.exit_code) from None
    except (ValueError, OSError) as err:  # one line and status 2 / 74 (cli.errors)
        raise SystemExit(errors.report(PROG, err)) from None


if __name__ == "__main__":  # python -m jaxtraffic.cli.train
    main()
