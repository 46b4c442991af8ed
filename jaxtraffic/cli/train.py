"""Train a gain policy: ``train.py ppo [flags]`` (the paper's PPO; also ``train.py [flags]``) or ``train.py
gradient [flags]`` (gradients through the simulator); ``train.py ALGO --help`` lists ALGO's flags.

tyro derives the flags from the config tree: one per leaf field the algorithm reads (``tree.fields_for``), named
after it (``--n-points`` sets ``plant.n_points``), with its default and its metadata's one-line ``help``.
``--config FILE.toml`` starts from a config file (a run's config.toml reproduces it), ``--recipe NAME`` from one of
the main job's runs (``paper.recipes``: the package's own config files; not with ``--config``); flags override it.
Without a subcommand, ``ppo`` is inserted, unless the config file or recipe is a gradient run's or ``--resume``
names a gradient run's directory. Ctrl-C or SIGTERM stops after the current chunk with its checkpoint saved (exit
130 / 143); ``--resume`` continues from it. ``--coordinator-address HOST:PORT --num-processes N --process-id
I`` (or the ``JAX_*`` variables) run N cooperating processes (docs/tutorials/cluster.md).
"""
from __future__ import annotations

import dataclasses
import math
import sys
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import tyro
from tyro import _errors as tyro_errors

from jaxtraffic.cli import errors
from jaxtraffic.cli.options import Cluster, exit_on_version, program
from jaxtraffic.paper.recipes import NAMES, recipe_tables
from jaxtraffic.platform import compile_cache, distributed
from jaxtraffic.runs.config import ALGOS, SECTIONS, RunConfig, TrainConfig, load_config
from jaxtraffic.runs.config.toml import read_tables
from jaxtraffic.runs.config.tree import fields_for, flag_sections, flag_tables, run_control
from jaxtraffic.runs.gradient.trainer import train_gradient
from jaxtraffic.runs.ppo.trainer import train
from jaxtraffic.runs.session import TrainingInterrupted, check_resumable

Tables = dict[str, dict[str, Any]]  # {section: {field: value}}, as a config file's tables
PROG = program("train.py")  # in messages: the program the user typed
# flags of the last release that are gone: what to give instead
REMOVED = {"--algo": "`train.py gradient` (or `train.py ppo`): the algorithm is the subcommand",
           "--seeds": "--num-seeds", "--network": "--hidden (layer sizes, e.g. 64 64)",
           "--lr-decay-steps": "--lr (the rate is constant)", "--lr-final": "--lr (the rate is constant)",
           "--certificate-weight": "nothing (the penalty is gone)", "--effort-weight": "nothing (the term is gone)"}
ABOUT = {"ppo": "Train the paper's PPO gain policy (the default subcommand).",
         "gradient": "Train a policy (gains, network or delay schedule) by gradients through the simulator."}
HELP = ("-h", "--help", "-H", "--help-verbose")
DESCRIPTION = (f"Train a gain policy: {PROG} ppo [flags] (also {PROG} [flags]) or {PROG} gradient [flags]; "
               f"{PROG} ALGO --help lists ALGO's flags, by config section; --recipe NAME starts from a run of "
               f"the main job ({', '.join(NAMES)}); --version: the version.")


GROUPS = {"plant": "the nominal training plant and its grid (physical constants: a --config file's [plant])",
          "env": "episodes, domain randomisation, reward shaping, observation",
          "ppo": "PPO (num_seeds: the population, num_envs: each member's)",
          "grad": "the gradient and CEM trainers", "run": "where, how long, the stop rule (the run control)"}


def flags_class(algo: str, base: TrainConfig) -> type:
    """The dataclass tyro derives ``train.py ALGO``'s flags from: one group per config section (a dataclass of the
    leaf fields ``algo`` reads there, ``tree.fields_for``, with ``base``'s values as defaults and their metadata's
    one-line help; its flags unprefixed), --config, --recipe and the cluster's flags."""
    hints = {s: typing.get_type_hints(cls) for s, cls in SECTIONS.items()}
    values = base.tables()
    groups: dict[str, list] = {}
    for s, f in fields_for(algo):
        groups.setdefault(s, []).append((f.name, _flag_type(hints[s][f.name], f, values[s][f.name]),
                                         dataclasses.field(default=values[s][f.name], metadata={
                                             "help": f.metadata.get("help")})))
    sections = []
    for s, leaves in groups.items():
        group = dataclasses.make_dataclass(s, leaves, frozen=True)
        group.__doc__ = GROUPS[s]
        sections.append((s, Annotated[group, tyro.conf.OmitArgPrefixes], dataclasses.field(default_factory=group)))
    cls = dataclasses.make_dataclass(algo, [*sections, (
        "config", Union[Path, None], dataclasses.field(default=None, metadata={  # noqa: UP007 (a runtime type)
            "help": "start from this config file (a run's config.toml); the flags given override it"})), (
        "recipe", Union[Literal[NAMES], None], dataclasses.field(default=None, metadata={  # noqa: UP007 (a runtime type)
            "help": f"start from the main job's run NAME ({', '.join(NAMES)}; not with --config); the flags given "
                    "override it"})), (
        "cluster", Annotated[Cluster, tyro.conf.OmitArgPrefixes], dataclasses.field(default_factory=Cluster))],
        frozen=True)
    cls.__doc__ = ABOUT[algo]
    return cls


def _flag_type(hint: Any, f: dataclasses.Field, value: Any) -> Any:
    """The type tyro parses a field's flag as: its choices, or its type; a boolean is one flag (``--quiet``,
    ``--no-require-certificate``: the opposite of its default), but both when a --config file changed it (so
    ``--quiet`` still works when the file says ``quiet = true``)."""
    if "choices" in f.metadata:
        return Literal[tuple(f.metadata["choices"])]
    if hint is bool and value is False and f.default is False:
        return Annotated[bool, tyro.conf.FlagCreatePairsOff]
    return hint


def _value_of(argv: list[str], flag: str) -> str | None:
    """The value of ``flag`` in ``argv`` (``--flag VALUE`` or ``--flag=VALUE``; the last one), else None."""
    value = None
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(flag + "="):
            value = arg.split("=", 1)[1]
    return value


def _start_tables(argv: list[str]) -> Tables:
    """The tables the command line starts from: the packaged recipe ``--recipe NAME``'s (``paper.recipes``) or the
    ``--config FILE``'s (the two are exclusive), else none."""
    name, config_file = _value_of(argv, "--recipe"), _value_of(argv, "--config")
    if name is not None and config_file is not None:
        raise ValueError("--recipe and --config both name the configuration to start from: give one (flags given "
                         "with either override it)")
    if name is not None:
        if name not in NAMES:
            raise ValueError(f"--recipe {name!r}: no such recipe; the recipes are: {', '.join(NAMES)}")
        return recipe_tables(name)
    return read_tables(config_file) if config_file else {}


def _default_algo(argv: list[str], from_file: Tables) -> str:
    """The subcommand of a command line without one: the --config file's algorithm, or the resumed run's, or PPO."""
    if "algo" in from_file.get("run", {}):
        return from_file["run"]["algo"]
    run_dir = Path(_value_of(argv, "--out-dir") or RunConfig.out_dir)
    if "--resume" in argv:
        try:
            return load_config(run_dir).run.algo
        except (ValueError, OSError):  # (the resume's checks say what is wrong with the directory)
            pass
    return "ppo"


def _out_dir(algo: str, tables: Tables) -> str:
    """The default run directory: runs/default (PPO), runs/gradient-POLICY."""
    policy = tables.get("grad", {}).get("policy", "gains")
    return f"runs/gradient-{policy}" if algo == "gradient" else RunConfig.out_dir


def _with_run(tables: Tables, algo: str) -> Tables:
    """``tables`` with the run's algorithm ``algo`` and, unless they give one, its default run directory."""
    return {**tables, "run": {"out_dir": _out_dir(algo, tables), **tables.get("run", {}), "algo": algo}}


def _base(algo: str, from_file: Tables) -> TrainConfig:
    """The defaults of ``train.py ALGO``'s flags: the --config file's values when the file is a run of ``algo``
    (or names none), else the defaults (a gradient file's fields need not make a valid PPO run)."""
    file = from_file if from_file.get("run", {}).get("algo", algo) == algo else {}
    return TrainConfig.make(**_with_run(file, algo))


def _given(argv: list[str], names: set[str]) -> set[str]:
    """The fields set by flags of ``argv`` (``--n-points``, ``--no-require-certificate``), by name."""
    given = set()
    for arg in argv:
        name = arg[2:].split("=", 1)[0].replace("-", "_") if arg.startswith("--") else ""
        name = name[3:] if name.startswith("no_") and name not in names else name
        if name in names:
            given.add(name)
    return given


def _split_commas(argv: list[str], tuple_flags: set[str]) -> list[str]:
    """``--hidden 64,64`` as ``--hidden 64 64`` (the comma form of the last release, still accepted)."""
    out: list[str] = []
    for arg in argv:
        flag, eq, value = arg.partition("=")
        if eq and flag in tuple_flags:
            out += [flag, *value.split(",")]
        elif out and out[-1] in tuple_flags and "," in arg:
            out += arg.split(",")
        else:
            out.append(arg)
    return out


def _refuse_removed(argv: list[str]) -> None:
    """``ValueError`` naming the new form of a flag of the last release that is gone (``REMOVED``)."""
    gone = [a.split("=")[0] for a in argv if a.split("=")[0] in REMOVED]
    if gone:
        raise ValueError(f"{gone[0]} was removed; use {REMOVED[gone[0]]}")


def _one_line(event: Any, algo: str, owner: dict[str, str]) -> None:
    """tyro's parse errors as one ``ValueError`` line (``cli.errors``: status 2) instead of its box; ``owner``:
    the subcommand of each flag."""
    if isinstance(event, tyro_errors.UnrecognizedArgs):
        other = [t for t in event.tokens if owner.get(t.split("=")[0], algo) != algo]
        if other:
            flag = other[0].split("=")[0]
            raise ValueError(f"{flag}: a flag of `{PROG} {owner[flag]}`, not of `{PROG} {algo}`"
                             + (" (its length is --grad-steps)" if flag == "--total-steps" else ""))
        raise ValueError(f"unrecognized arguments: {' '.join(event.tokens)} (see {event.prog} --help)")
    if isinstance(event, tyro_errors.InvalidChoice):
        raise ValueError(f"{event.argument.display_name()}: invalid choice {event.value!r} "
                         f"(choose from {', '.join(event.choices)})")
    if isinstance(event, tyro_errors.BadValue):
        why = "too few values" if event.reason == "too_few_values" else f"cannot take {event.offending_value!r}"
        raise ValueError(f"{event.argument.display_name()}: {why}")
    if isinstance(event, tyro_errors.InstantiationFailure):
        where = f"{event.argument.display_name()}: " if event.argument is not None else ""
        raise ValueError(where + " ".join(event.message.split(" Got errors:")[0].split()))


def parse(argv: list[str] | None = None) -> tuple[TrainConfig, Cluster, dict[str, str]]:
    """The training configuration of the command line ``argv`` (default ``sys.argv[1:]``), its cluster flags,
    and the fields its flags and its --config file set, each with where (``--lr``, ``lr in FILE``)."""
    argv = ["--help" if a in ("-H", "--help-verbose") else a for a in (sys.argv[1:] if argv is None else argv)]
    _refuse_removed(argv)
    exit_on_version(argv, PROG)
    from_file = _start_tables(argv)
    recipe_name = _value_of(argv, "--recipe")
    config_file = _value_of(argv, "--config") or (f"jaxtraffic/paper/recipes/{recipe_name}.toml" if recipe_name
                                                   else None)
    if not argv or argv[0] not in (*ALGOS, *HELP):
        argv.insert(0, _default_algo(argv, from_file))
    try:  # the file's values are checked here first: an error names the file
        bases = {a: _base(a, from_file) for a in ALGOS}
    except (TypeError, ValueError) as err:
        raise ValueError(f"{config_file}: {err}" if config_file else str(err)) from None
    classes = {a: flags_class(a, bases[a]) for a in ALGOS}
    algo = argv[0] if argv[0] in ALGOS else "ppo"
    section = flag_sections(algo)
    tuples = {"--" + f.name.replace("_", "-") for _, f in fields_for(algo) if "tuple" in str(f.type)}
    argv = _split_commas(argv, tuples)
    # a type built at run time (the flag classes are): a value to mypy, not a type alias
    commands: Any = Union[tuple(Annotated[classes[a], tyro.conf.subcommand(a, description=ABOUT[a])]  # noqa: UP007
                                for a in ALGOS)]
    owner = {"--" + f.name.replace("_", "-"): a for a in reversed(ALGOS) for _, f in fields_for(a)}
    with tyro_errors.on_parse_error(lambda event: _one_line(event, algo, owner)):
        flags = tyro.cli(commands, args=argv, prog=PROG, default=classes["ppo"](), description=DESCRIPTION)
    given = _given(argv[1:], set(section))
    values = {k: getattr(getattr(flags, section[k]), k) for k in given}
    origin = {k: f"{k} in {config_file}" for t in from_file.values() for k in t if k != "algo"}
    origin.update({k: "--" + k.replace("_", "-") for k in given})
    if values.get("min_wave_speed") == -math.inf:  # the paper's rule alone (stored as null in the JSON outputs)
        values["min_wave_speed"] = None
    tables: Tables = {s: dict(t) for s, t in from_file.items()}  # the file's, then the flags over them
    for s, t in flag_tables(algo, values).items():
        tables[s] = {**tables.get(s, {}), **t}
    return TrainConfig.make(**_with_run(tables, algo)), flags.cluster, origin


def config_from_args(argv: list[str] | None = None) -> TrainConfig:
    """The training configuration the command line ``argv`` (default: the process's) describes."""
    return parse(argv)[0]


def resumed_config(config: TrainConfig, given: set[str] | dict) -> TrainConfig:
    """On --resume: the run's saved configuration, with the run-control fields given (``tree.run_control``, by
    flags or a --config file; ``given`` maps each to where it was given, ``parse``) applied, and recorded in the
    run's config.json; a field that would change the trained problem is an error."""
    saved = load_config(config.run.out_dir)
    if saved.run.algo != config.run.algo:
        raise ValueError(f"{config.run.out_dir} holds a {saved.run.algo} run: resume it with "
                         f"`{PROG} {saved.run.algo} --resume`")
    control = run_control(saved.run.algo)
    new, old = config.tables(), saved.tables()
    section = flag_sections(saved.run.algo)
    where = {k: v for k, v in given.items() if isinstance(v, str) and v.startswith(("--", f"{k} in "))} \
        if isinstance(given, dict) else {}  # (parse's origins; a dict of values says only which were given)
    owners = {k: section.get(k) or next(s for s in new if k in new[s]) for k in given  # in the order given
              if k in section or where.get(k, "--").count(" in ")}  # (a file may set fields without a flag)
    changed = [f"{_label(k, where)} {new[s][k]!r} (the run's value: {old[s][k]!r})" for k, s in owners.items()
               if k not in control.get(s, ()) and new[s][k] != old[s][k]]
    if changed:
        flags = "these flags" if all(_label(k, where).startswith("--") for k in owners) else "these settings"
        raise ValueError(f"--resume continues the run with its saved configuration; {flags} would change it: "
                         + ", ".join(changed) + "; drop them, or start a new run (--overwrite clears this one)")
    kept: dict[str, dict[str, Any]] = {}
    for k, s in owners.items():
        if k in control.get(s, ()):
            kept.setdefault(s, {})[k] = new[s][k]
    return saved.updated(**{**kept, "run": {**kept.get("run", {}), "resume": True, "out_dir": config.run.out_dir}})


def _label(name: str, where: dict[str, str]) -> str:
    """How a resumed field was given: ``--lr`` (a flag), ``lr in FILE =`` (a --config file)."""
    origin = where.get(name, "--" + name.replace("_", "-"))
    return origin if origin.startswith("--") else origin + " ="


def main(argv: list[str] | None = None) -> Path:
    """Parse flags, start ``jax.distributed`` if asked (``jaxtraffic.platform.distributed``: before anything
    runs on a device), train, return the run directory. Exit status 2 for invalid flags or a broken
    run directory, 74 for an OS error (``cli.errors``), 130 / 143 after SIGINT / SIGTERM (``runs.ppo.trainer``)."""
    try:
        with errors.interrupt_is_130(PROG):
            config, cluster, given = parse(argv)
        distributed.initialize(*cluster.values())
        compile_cache.enable()  # before the first compilation (jaxtraffic.platform.compile_cache)
        if config.run.resume:
            check_resumable(Path(config.run.out_dir))
            config = resumed_config(config, given)
        return train_gradient(config) if config.run.algo == "gradient" else train(config)
    except TrainingInterrupted as exc:  # the trainer has said what is saved
        raise SystemExit(exc.exit_code) from None
    except (ValueError, OSError) as err:  # one line and status 2 / 74 (cli.errors)
        raise SystemExit(errors.report(PROG, err)) from None


if __name__ == "__main__":  # python -m jaxtraffic.cli.train
    main()
