"""A run's config as TOML: ``write_config(config, path)`` (every run's config.toml) and ``read_config(path)``.

One table per section (``[plant]``, ``[env]``, ``[ppo]``, ``[grad]``, ``[run]``), one key per field, named as
the field. TOML has no null: a field that is ``None`` is left out (it reads back as its default, ``None``),
but ``min_wave_speed``, whose ``None`` is written ``-inf`` as on the command line. A file may give any subset of
the fields (the rest take their defaults; ``grad``'s the policy's; ``resume`` and ``overwrite`` are not
written); ``read_config(p)`` of a file that
``write_config`` wrote is the config it was written from.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import tomli_w

from jaxtraffic.io.files import atomic_write_text, read_text
from jaxtraffic.runs.config.tree import SECTIONS, TrainConfig, leaf_fields

CONFIG_TOML = "config.toml"
ACTIONS = ("resume", "overwrite")  # what a command does to its run directory, not what the run is: not written


def config_toml(config: TrainConfig) -> str:
    """The TOML text of ``config``."""
    tables: dict[str, dict[str, Any]] = {}
    for s in SECTIONS:
        section = getattr(config, s)
        table = {}
        for f in leaf_fields(s):
            if f.name in ACTIONS:
                continue
            value = getattr(section, f.name)
            if value is None and f.name == "min_wave_speed":
                value = -math.inf
            if value is not None:
                table[f.name] = list(value) if isinstance(value, tuple) else value
        tables[s] = table
    return tomli_w.dumps(tables)


def write_config(config: TrainConfig, path: str | Path) -> None:
    """Write ``config`` as TOML to ``path`` (atomically)."""
    atomic_write_text(path, config_toml(config))


def tables_of_toml(data: dict[str, Any], where: str) -> dict[str, dict[str, Any]]:
    """The fields a TOML document gives, by table (``{section: {field: value}}``); ``ValueError`` for an unknown
    table or key."""
    tables: dict[str, dict[str, Any]] = {}
    for s, table in data.items():
        if s not in SECTIONS or not isinstance(table, dict):
            raise ValueError(f"{where}: unknown table [{s}] (the tables are {', '.join(SECTIONS)})")
        names = {f.name for f in leaf_fields(s)}
        for k, v in table.items():
            if k not in names:
                raise ValueError(f"{where}: [{s}] has no field {k!r}")
            if s == "run" and k in ACTIONS:  # what a command does to a run directory: the command line's alone
                raise ValueError(f"{where}: [run] {k} is an action on the run directory, not a setting; give "
                                 f"--{k} on the command line instead")
            tables.setdefault(s, {})[k] = (None if k == "min_wave_speed" and v == -math.inf
                                           else tuple(v) if isinstance(v, list) else v)
    return tables


def read_tables(path: str | Path) -> dict[str, dict[str, Any]]:
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
