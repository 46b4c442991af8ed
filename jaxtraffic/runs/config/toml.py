"""A run's config files: config.toml (``write_config`` / ``read_config``: the run's truth, what a user reads and
edits) and config.json (``config_json``: the machine copy, every field and the facts of the run); ``load_config``.

A config file is one table per section (``[plant]``, ``[env]``, ``[ppo]``, ``[grad]``, ``[run]``), one key per
field, named as the field, and ``config_version``. It holds what differs from the defaults of its algorithm and
gradient policy (``TrainConfig.defaults``; ``[run] algo`` always, ``[grad] policy`` for a gradient run), so a
field it lacks is at its default: a file written before a field existed loads with that field at its default, and
a file of an older version is brought to today's by the numbered ``MIGRATIONS`` (where a meaning changed). TOML has
no null: ``min_wave_speed``'s ``None`` is written ``-inf``, as on the command line; ``resume`` and ``overwrite``
(actions on the run directory) are not written. ``read_config(p)`` of a file ``write_config`` wrote is the config
it was written from.

``load_config(run_dir)`` reads the run's config.toml (a run without one: its config.json). An edit of the
run-control fields (``tree.run_control``) is honoured; an edit of any other field (what the checkpoint was trained
on) is refused in one line naming it, by comparison with config.json.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import tomli_w

from jaxtraffic.io.files import atomic_write_text, read_json, read_text
from jaxtraffic.runs.config.tree import CONFIG_VERSION, SECTIONS, TrainConfig, leaf_fields, run_control

Tables = dict[str, dict[str, Any]]  # {section: {field: value}}
CONFIG_TOML, CONFIG_JSON = "config.toml", "config.json"
ACTIONS = ("resume", "overwrite")  # what a command does to its run directory, not what the run is: not written
HEADER = ("# This run's configuration: the fields that differ from the defaults (`train.py ALGO --help` lists them\n"
          "# all). `train.py --config THIS_FILE` trains it again. On --resume an edit of the run control ([run]\n"
          "# out_dir, total_steps, max_wall_s, the stop rule, ...) applies; an edit of any other field is refused.\n")


def _v3(tables: Tables) -> Tables:
    """Version 3 -> 4: the controller's own grid moved from [env] (None: the plant's) to [grad] (0: the plant's)."""
    env = dict(tables.get("env", {}))
    if "controller_points" not in env:
        return tables
    return {**tables, "env": env, "grad": {**tables.get("grad", {}), "controller_points": env.pop(
        "controller_points") or 0}}


def _v4(tables: Tables) -> Tables:
    """Version 4 -> 5: the initial amplitudes ([env] amp_range, [grad] train_amplitudes) in veh/km, not veh/m (the
    unit of every other density a user sees)."""
    moved = {"env": "amp_range", "grad": "train_amplitudes"}
    return {s: {k: (type(v)(round(a * 1e3, 9) for a in v) if moved.get(s) == k and v is not None else v)
                for k, v in table.items()} for s, table in tables.items()}


def _v5(tables: Tables) -> Tables:
    """Version 5 -> 6: the training sensor noise moved from [grad] to [env] (PPO's environment sees it too; a PPO
    run of version 5 trained without it, whatever its [grad] said)."""
    grad = dict(tables.get("grad", {}))
    if "train_sensor_noise" not in grad:
        return tables
    noise = grad.pop("train_sensor_noise")
    moved = {} if tables.get("run", {}).get("algo") == "ppo" else {"train_sensor_noise": noise}
    return {**tables, "grad": grad, "env": {**tables.get("env", {}), **moved}}


# version n's tables -> version n + 1's. A config file holds only what differs from the defaults, so a changed
# default, or a field whose meaning changed, is a new version whose migration writes the old value or meaning into
# the older files' tables (CONFIG_VERSION + 1, its function here).
MIGRATIONS: dict[int, Callable[[Tables], Tables]] = {3: _v3, 4: _v4, 5: _v5}


def migrate(tables: Tables, version: Any, where: str) -> Tables:
    """``tables`` of config ``version`` as today's (``MIGRATIONS`` in turn); ``ValueError`` for another version."""
    if not isinstance(version, int) or isinstance(version, bool) or not min(MIGRATIONS) <= version <= CONFIG_VERSION:
        raise ValueError(f"{where}: config version {version!r}; this jaxtraffic reads versions {min(MIGRATIONS)} to "
                         f"{CONFIG_VERSION} (a newer jaxtraffic wrote it, or it was edited)")
    for v in range(version, CONFIG_VERSION):
        tables = MIGRATIONS[v](tables)
    return tables


def config_json(config: TrainConfig, **extra: Any) -> dict[str, Any]:
    """The content of a run's config.json: the tree (``{section: {field: value}}``, every field) and its version,
    plus ``extra`` facts about the run (devices, jax version, ...)."""
    return {"version": CONFIG_VERSION, "config": dataclasses.asdict(config), **extra}


def _toml_value(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(map(_toml_value, value)) + "]"
    return tomli_w.dumps({"v": value})[len("v = "):].strip()


def config_toml(config: TrainConfig, header: str = HEADER) -> str:
    """The TOML text of ``config``: the fields that differ from ``config.defaults()``, after ``header``."""
    own, base = config.tables(), config.defaults().tables()
    always = {("run", "algo"), *((("grad", "policy"),) if config.run.algo == "gradient" else ())}
    lines = [header + f"config_version = {CONFIG_VERSION}"]
    for s in SECTIONS:
        table = [f"{k} = {_toml_value(-math.inf if v is None else v)}" for k, v in own[s].items()
                 if k not in ACTIONS and (v != base[s][k] or (s, k) in always)]
        lines += [f"\n[{s}]", *table] if table else []
    return "\n".join(lines) + "\n"


def write_config(config: TrainConfig, path: str | Path) -> None:
    """Write ``config`` as TOML to ``path`` (atomically)."""
    atomic_write_text(path, config_toml(config))


def tables_of_toml(data: dict[str, Any], where: str) -> Tables:
    """The fields a TOML document gives, by table (``{section: {field: value}}``), brought to today's version (a
    document without ``config_version`` was written before it: version 3 or 4); ``ValueError`` for an unknown
    table or key."""
    data = dict(data)
    version = data.pop("config_version", 3)
    tables: Tables = {}
    for s, table in data.items():
        if s not in SECTIONS or not isinstance(table, dict):
            raise ValueError(f"{where}: unknown table [{s}] (the tables are {', '.join(SECTIONS)})")
        tables[s] = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    tables = migrate(tables, version, where)
    for s, table in tables.items():
        names = {f.name for f in leaf_fields(s)}
        for k, v in table.items():
            if k not in names:
                raise ValueError(f"{where}: [{s}] has no field {k!r}")
            if s == "run" and k in ACTIONS:  # what a command does to a run directory: the command line's alone
                raise ValueError(f"{where}: [run] {k} is an action on the run directory, not a setting; give "
                                 f"--{k} on the command line instead")
            if k == "min_wave_speed" and v == -math.inf:
                table[k] = None
    return tables


def read_tables(path: str | Path) -> Tables:
    """The fields a TOML config file gives, by table."""
    try:
        data = tomllib.loads(read_text(path))  # a regular file of at most CONFIG_LIMIT bytes
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise ValueError(f"{path}: unreadable or not valid TOML ({type(err).__name__}: {err})") from None
    return tables_of_toml(data, str(path))


def read_config(path: str | Path) -> TrainConfig:
    """The ``TrainConfig`` of a TOML config file (fields it does not give: their defaults)."""
    try:
        return TrainConfig.make(**read_tables(path))
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {err}") from None


def _from_json(f: dataclasses.Field, v: Any) -> Any:
    """A field's value as JSON holds it: a list is a tuple; a null float that cannot be None is inf (JSON has no
    inf: max_wall_s, val_target)."""
    return math.inf if v is None and str(f.type) == "float" else tuple(v) if isinstance(v, list) else v


def config_from_json(data: Any, where: str = CONFIG_JSON) -> TrainConfig:
    """The ``TrainConfig`` of a config.json's content, brought to today's version (``migrate``); a field it lacks
    is at its default, a key of a field that no longer exists is ignored."""
    tree = data.get("config") if isinstance(data, dict) else None
    if not isinstance(tree, dict) or not all(isinstance(t, dict) for t in tree.values()):
        flat = isinstance(data, dict) and "settings" in data
        raise ValueError(f"{where}: not a config tree written by train.py" + (
            " (flat settings: written before the config tree, which this jaxtraffic cannot read)" if flat else ""))
    if "algo" in tree and "ppo" not in tree:
        raise ValueError(f"{where}: an 'algo' section (written before PPO's settings were the 'ppo' section), "
                         "which this jaxtraffic cannot read")
    tree = migrate(tree, data.get("version"), where)
    tables: Tables = {}
    for s in SECTIONS:
        saved = tree.get(s, {})
        tables[s] = {f.name: _from_json(f, saved[f.name]) for f in leaf_fields(s) if f.name in saved
                     and (saved[f.name] is not None or "None" in str(f.type) or str(f.type) == "float")}
    try:
        return TrainConfig.make(**tables)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from None


def load_config(run_dir: str | Path) -> TrainConfig:
    """The ``TrainConfig`` of a run directory: its config.toml (an edit of the run control honoured, of another
    field refused in one line, ``check_edit``), or, in a run without one, its config.json."""
    toml, machine = Path(run_dir) / CONFIG_TOML, Path(run_dir) / CONFIG_JSON
    if not machine.exists() and not toml.exists():
        raise FileNotFoundError(f"{run_dir} is not a run directory (no {CONFIG_TOML}, no {CONFIG_JSON})")
    trained = config_from_json(read_json(machine), str(machine)) if machine.exists() else None
    if not toml.exists():
        assert trained is not None  # (one of the two exists)
        return trained
    config = read_config(toml)
    if trained is not None:
        check_edit(config, trained, toml)
    return config


def check_edit(config: TrainConfig, trained: TrainConfig, where: Path) -> None:
    """``ValueError`` naming the first field ``config`` (a run's config.toml) changes from ``trained`` (its
    config.json) that a resume may not change (all but ``tree.run_control``)."""
    control = run_control(trained.run.algo)
    now, then = config.tables(), trained.tables()
    for s in SECTIONS:
        for k in now[s]:
            if k not in control.get(s, ()) and now[s][k] != then[s][k]:
                raise ValueError(f"{where}: [{s}] {k} = {now[s][k]!r}, but the run's {CONFIG_JSON} (what it was "
                                 f"trained with) says {then[s][k]!r}; only the run control may be edited: restore it, "
                                 f"or train a new run (--config {where} --out-dir NEW)")
