"""A run's configuration as a TOML file: ``config.toml`` in every run directory, the paper's recipes
(``jaxtraffic/paper/recipes/``) and ``train.py --config FILE``.

The file holds the tree, one table per section (``[plant]``, ``[env]``, ``[algo]``, ``[grad]``, ``[run]``), every
field by its name but those only the other algorithm reads (``ONLY_FOR``; they keep their defaults). TOML has no
null: a field left unset (``None``) is left out, and ``min_wave_speed``'s "no wave-speed condition" is written
``-inf``. ``read_config`` rejects unknown sections and fields, and every value passes the tree's checks
(``runs.config.checks``) as if given on the command line.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import tomllib

from jaxtraffic.io.files import atomic_write_text
from jaxtraffic.runs.config.tree import CONFIG_VERSION, ONLY_FOR, SECTIONS, TrainConfig

CONFIG_TOML = "config.toml"
_NONE_AS_MINUS_INF = {"min_wave_speed"}  # None means "off"; TOML writes it as -inf


def _value(x: Any) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        return ("inf" if x > 0 else "-inf") if math.isinf(x) else "nan" if math.isnan(x) else repr(x)
    if isinstance(x, str):
        return json.dumps(x)  # a TOML basic string uses JSON's escapes
    if isinstance(x, (tuple, list)):
        return "[" + ", ".join(_value(v) for v in x) + "]"
    raise TypeError(f"cannot write {x!r} ({type(x).__name__}) to TOML")


def config_toml(config: TrainConfig) -> str:
    """The TOML text of ``config`` (``read_config`` reads it back to an equal config)."""
    lines = ["# jaxtraffic training configuration: python train.py --config THIS_FILE [flags overriding it]",
             f"version = {CONFIG_VERSION}", ""]
    other = ONLY_FOR["ppo" if config.run.algo == "gradient" else "gradient"]
    for name in SECTIONS:
        table = []
        for f in dataclasses.fields(SECTIONS[name]):
            value = getattr(getattr(config, name), f.name)
            if value is None and f.name in _NONE_AS_MINUS_INF:
                value = -math.inf
            if value is not None and f.name not in other:
                table.append(f"{f.name} = {_value(value)}")
        lines += [f"[{name}]", *table, ""] if table else []
    return "\n".join(lines)


def config_from_toml(text: str, where: str = "config.toml") -> TrainConfig:
    """The ``TrainConfig`` of a TOML text; ``ValueError`` naming ``where`` for anything else."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{where}: not valid TOML ({err})") from None
    version = data.pop("version", None)
    if version != CONFIG_VERSION:
        raise ValueError(f"{where}: configuration version {version!r}, this jaxtraffic reads version "
                         f"{CONFIG_VERSION} (a file written by train.py, or one of jaxtraffic/paper/recipes/)")
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise ValueError(f"{where}: unknown section(s) {unknown}; the sections are {list(SECTIONS)}")
    sections = {}
    for name, cls in SECTIONS.items():
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise ValueError(f"{where}: [{name}] must be a table")
        known = {f.name for f in dataclasses.fields(cls)}
        if set(table) - known:
            raise ValueError(f"{where}: unknown field(s) {sorted(set(table) - known)} in [{name}]")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
        values = {k: None if k in _NONE_AS_MINUS_INF and v == -math.inf else v for k, v in values.items()}
        try:
            sections[name] = cls(**values)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: [{name}]: {err}") from None
    try:
        return TrainConfig(**sections)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from None


def read_config(path: str | Path) -> TrainConfig:
    """The ``TrainConfig`` of a TOML file, or of a run directory (its config.toml)."""
    path = Path(path)
    if path.is_dir():
        path = path / CONFIG_TOML
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such configuration file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: unreadable ({type(err).__name__}: {err})") from None
    return config_from_toml(text, str(path))


def write_config(config: TrainConfig, path: str | Path) -> None:
    """Write ``config`` as TOML to ``path`` (atomically)."""
    atomic_write_text(Path(path), config_toml(config))
