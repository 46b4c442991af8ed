"""Files written whole or not at all, and JSON with non-finite numbers: the lowest layer's I/O.

Every write goes to a temporary file in the same directory (mode 0666 less the umask, like any other
file), is flushed and fsynced, then ``os.replace``d over the target, so an interruption never leaves a
half-written file; a temporary file left by a killed process (``.*.tmp``) is removed by
``clean_stale_tmp``.

Every config and run file is read by ``read_regular`` (``read_text``, ``read_json``): a regular file only (a FIFO
is opened without blocking, then refused, like a device or a directory), at most ``limit`` bytes; a bad one is a
``ValueError`` naming it.

JSON outputs (``to_jsonable``): ``null`` means "never" / "none" / unbounded (+inf: a time that is
never reached, no wall-clock limit); a value that could not be computed, NaN, is the string
``"nan"``, and -inf is ``"-inf"``. ``from_jsonable`` reads them back as floats.

Imports nothing of jaxtraffic: every layer may use it.
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import jax
import numpy as np

__all__ = ["CONFIG_LIMIT", "as_lists", "atomic_write_bytes", "atomic_write_text", "clean_stale_tmp", "dumps_json",
           "from_jsonable", "read_json", "read_regular", "read_text", "to_jsonable", "write_json"]

CONFIG_LIMIT = 2**20  # bytes: a config file (TOML, config.json), a summary: a few kB in practice
KINDS = {stat.S_IFIFO: "a FIFO (named pipe)", stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device",
         stat.S_IFDIR: "a directory", stat.S_IFSOCK: "a socket"}


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` at ``path`` atomically (module docstring); an ``OSError`` names the file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp creates 0600: results readable like any file
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError) and err.filename is None:  # e.g. ENOSPC from write: name the file
            raise type(err)(err.errno, err.strerror, str(path)) from None
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """``atomic_write_bytes`` of UTF-8 text."""
    atomic_write_bytes(path, text.encode())


def clean_stale_tmp(run_dir: str | Path, names: Iterable[str]) -> list[Path]:
    """Remove the temporary files that a killed ``atomic_write_bytes`` of one of ``names`` left in ``run_dir``
    (``.<name>.<8 random characters>.tmp``, regular files only; anything else, a user's ``.x.tmp`` included, is
    left alone); returns them. Call it only when no other process writes to the directory."""
    pattern = re.compile("|".join(rf"\.{re.escape(n)}\.[A-Za-z0-9_]{{8}}\.tmp" for n in names))
    stale = sorted(p for p in Path(run_dir).glob(".*.tmp")
                   if pattern.fullmatch(p.name) and stat.S_ISREG(p.lstat().st_mode))
    for p in stale:
        p.unlink(missing_ok=True)
    return stale


def read_regular(path: str | Path, limit: int = CONFIG_LIMIT, follow: bool = True) -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``limit`` bytes; ``ValueError`` naming it
    otherwise (a FIFO, a device, a directory, too large), ``OSError`` if it cannot be opened. ``follow``
    False: a symbolic link is refused too (a run's own files)."""
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)  # O_NONBLOCK: opening a FIFO does not wait for a writer
    except OSError as err:
        if not follow and os.path.islink(path):
            raise ValueError(f"{path}: a symbolic link, not a regular file (refused)") from None
        if err.filename is None:
            raise type(err)(err.errno, err.strerror, str(path)) from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = KINDS.get(stat.S_IFMT(st.st_mode), "not a regular file")
            raise ValueError(f"{path}: {kind}, not a regular file (refused)")
        if st.st_size > limit:
            raise ValueError(f"{path}: {st.st_size} bytes, more than the {limit} bytes such a file may hold")
    except BaseException:
        os.close(fd)
        raise
    with os.fdopen(fd, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:  # it grew while being read
        raise ValueError(f"{path}: more than the {limit} bytes such a file may hold")
    return data


def read_text(path: str | Path, limit: int = CONFIG_LIMIT, follow: bool = True) -> str:
    """``read_regular`` decoded as UTF-8 (``ValueError`` naming the file if it is not)."""
    data = read_regular(path, limit, follow)
    try:
        return data.decode()
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text ({err})") from None


def to_jsonable(x: Any) -> Any:
    """Convert numpy/jax scalars and arrays to JSON types (``as_lists``: float32 values at their shortest
    decimal). +inf becomes None (null: "never", unbounded), NaN the string "nan" (not computable: kept distinct
    from null), -inf "-inf"."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, (jax.Array, np.ndarray, np.generic)):
        return to_jsonable(as_lists(x))
    if isinstance(x, float) and not math.isfinite(x):
        return "nan" if math.isnan(x) else (None if x > 0 else "-inf")
    return x


def as_lists(x: Any) -> Any:
    """An array as nested Python lists (a scalar for a 0-d one), like ``tolist``, but a float32 (or float16)
    value becomes the shortest decimal that rounds back to it (numpy's unique repr: 0.021665478, not float64's
    0.021665478125214577): what a reader gets with ``np.float32(x)``, in about half the characters of JSON.
    Non-finite values stay floats."""
    a = np.asarray(x)
    if a.dtype not in (np.float32, np.float16):
        return a.tolist()
    flat = np.empty(a.size, object)
    flat[:] = [float(str(v)) for v in a.ravel()]  # (str of a numpy float32 scalar: its shortest unique repr)
    return flat.reshape(a.shape).tolist()


NONFINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def from_jsonable(x: Any) -> Any:
    """Inverse of ``to_jsonable`` for non-finite values: the strings "nan", "inf", "-inf" become
    floats (anywhere in dicts and lists); null stays None."""
    if isinstance(x, dict):
        return {k: from_jsonable(v) for k, v in x.items()}
    if isinstance(x, list):
        return [from_jsonable(v) for v in x]
    if isinstance(x, str) and x in NONFINITE:
        return NONFINITE[x]
    return x


# an indented list of numbers, booleans and nulls only: "[" then a newline (never inside a JSON string, whose
# newlines are escaped), the scalars one a line, then "]"
_SCALAR = r"(?:-?\d[\d.eE+-]*|true|false|null)"
_SCALAR_LIST = re.compile(r"\[\n\s*" + _SCALAR + r"(?:,\n\s*" + _SCALAR + r")*\n\s*\]")


def dumps_json(obj: Any) -> str:
    """``obj`` as strict JSON text (``to_jsonable``), indented, each list of scalars on one line (a third of the
    bytes of one number a line for the recorded series), ending in a newline."""
    text = json.dumps(to_jsonable(obj), indent=1, sort_keys=False, allow_nan=False)
    return _SCALAR_LIST.sub(lambda m: "[" + ", ".join(v.strip() for v in m.group(0)[1:-1].split(",")) + "]",
                            text) + "\n"


def write_json(path: str | Path, obj: Any) -> None:
    """``obj`` as strict JSON (``dumps_json``: indented, lists of scalars on one line), written atomically."""
    atomic_write_text(path, dumps_json(obj))


def read_json(path: str | Path, limit: int = CONFIG_LIMIT, follow: bool = True) -> Any:
    """The JSON content of ``path`` (``read_text``); ``ValueError`` naming it if it is unreadable or not JSON."""
    try:
        return json.loads(read_text(path, limit, follow))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise ValueError(f"{path}: unreadable or not valid JSON ({type(err).__name__}: {err})") from None
