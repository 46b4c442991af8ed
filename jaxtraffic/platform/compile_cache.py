"""A persistent XLA compilation cache for the command-line jobs (``train.py``, ``evaluate.py``).

Compiling the PPO chunk, its initialisation and the evaluation rollouts takes about half of a
default training's wall time on a 2-core CPU (docs/model.md section 19.3). JAX can keep compiled executables
on disk and load them in a later process instead of compiling again; a loaded executable is the
program a fresh compilation would produce, so results are bit-identical with and without it.

``enable(...)`` turns jax's cache on unless the user already chose:

  * ``JAX_COMPILATION_CACHE_DIR`` set, or ``jax_compilation_cache_dir`` already configured: left as
    it is (jax uses the user's directory and settings; nothing here overrides them);
  * ``JAXTRAFFIC_COMPILATION_CACHE`` = ``0`` / ``off`` / ``false``: no cache;
  * ``JAXTRAFFIC_COMPILATION_CACHE`` = a path: that directory;
  * otherwise ``$XDG_CACHE_HOME/jaxtraffic/xla`` (``~/.cache/jaxtraffic/xla``).

The directory is created private to the user (mode 0700: jax executes what it loads from there,
so it must not be writable by others); an existing directory that others can write to, that another
user owns or that is a symbolic link is not used, and a path that cannot be created leaves the cache off;
in each case a one-line warning says so. Its size is bounded (``MAX_BYTES``; least recently used
entries are evicted), which also makes jax guard every read and write with a file lock, so that
processes running at once (several trainings, the processes of a multi-process run) never read
a half-written entry. Only programs that took at least ``MIN_COMPILE_S`` to compile are stored.

The library itself (``import jaxtraffic``) never enables the cache: writing to a user's home
directory is the command-line jobs' choice, and a library user calls ``enable()`` explicitly.
"""

from __future__ import annotations

import os
import stat
import sys
from collections.abc import Mapping
from pathlib import Path

ENV = "JAXTRAFFIC_COMPILATION_CACHE"
MAX_BYTES = 2 << 30  # 2 GiB; a default training + evaluation stores about 30 MB
MIN_COMPILE_S = 0.5  # programs that compile faster are not worth a disk entry
_OFF = ("0", "off", "false", "no")

__all__ = ["ENV", "MAX_BYTES", "MIN_COMPILE_S", "default_dir", "enable", "private", "usable"]


def default_dir(env: Mapping[str, str] | None = None) -> Path:
    """``$XDG_CACHE_HOME/jaxtraffic/xla``, or ``~/.cache/jaxtraffic/xla``."""
    env = os.environ if env is None else env
    base = env.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxtraffic" / "xla"


def private(where: Path) -> bool:
    """Whether the cache directory ``where`` is a real directory (not a link) of this user that no other user
    can write to (jax executes what it loads from there); if not, say so on stderr (one line)."""
    st = where.lstat()
    why = ("is a symbolic link" if stat.S_ISLNK(st.st_mode) else "is not a directory" if not stat.S_ISDIR(st.st_mode)
           else f"belongs to another user (uid {st.st_uid})" if st.st_uid != os.getuid()
           else f"is writable by other users (mode {st.st_mode & 0o777:o})" if st.st_mode & 0o022 else None)
    if why:
        print(f"warning: the compilation cache {where} {why}; running without a cache (use a private directory "
              f"of your own: chmod go-w it, or set {ENV})", file=sys.stderr)
        return False
    return True


def usable(where: Path) -> bool:
    """Create the cache directory ``where`` (0700) if needed; whether it can be used (``private``); if not, one
    line on stderr says why (e.g. a read-only home: the job then runs without a cache)."""
    try:
        where.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as err:
        print(f"warning: the compilation cache {where} cannot be created ({err.strerror or err}); running without "
              f"a cache (set {ENV} to a writable directory, or to 0 to silence this)", file=sys.stderr)
        return False
    return private(where)


def enable(path: str | os.PathLike | None = None, env: Mapping[str, str] | None = None) -> Path | None:
    """Turn on jax's persistent compilation cache (see the module docstring for the rules).

    ``path``: the directory (default: from ``JAXTRAFFIC_COMPILATION_CACHE``, else ``default_dir``).
    Returns the directory in use, or None when the cache is left off or left to the user's own
    jax settings. Call it before the first compilation: jax decides once per process whether
    it uses a cache.
    """
    import jax

    env = os.environ if env is None else env
    if env.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:  # type: ignore[attr-defined]
        return None  # the user's own cache: not ours to change
    choice = env.get(ENV, "").strip()
    if path is None and choice.lower() in _OFF:
        return None
    try:
        import filelock  # noqa: F401  (jax needs it for a size-bounded cache)
    except ImportError:
        return None
    where = Path(path if path is not None else (choice or default_dir(env))).expanduser()
    if not usable(where):
        return None
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    return where
