"""``evaluate.py``'s outputs made whole or not at all, only where the job may write, and its signals handled
like the trainers'.

``--out`` must be a folder the job owns (``check_out``): one that does not exist yet, an empty folder, or a
folder holding a report ``evaluate.py`` published before (recognised by its marker file, ``MARKER``, written
into every report). Anything else (a project folder, a home, a dangling symbolic link, ``""``) is refused
before any work starts; nothing here ever removes a folder the job did not write.

``Staging(out)`` takes one lock per output folder (``.NAME.jaxtraffic-lock`` beside it, opened without following
a symbolic link: a second job on the same ``--out`` is refused), removes stale staging folders of earlier jobs on
the same ``--out`` (recognised by their own marker and their owner, while the lock proves no live job uses them),
and creates a fresh staging folder with ``tempfile.mkdtemp`` in the parent (mode 0700, an unpredictable name).
``publish()`` then moves each entry written there into ``out``, replacing the entry of the same name (entries of
``out`` the job did not write are left alone), with the signals deferred and every step undone if one fails:
``out`` ends up holding the new report or, unchanged, the previous one. ``discard()`` removes the staging folder.

``signals_raise()`` turns SIGINT, SIGTERM and SIGHUP into ``Stopped`` in the main thread (a
``BaseException``: no ``except Exception`` swallows it). ``leave(code)`` exits with ``code``; while one
of the evaluation's background threads (``paper.driver._Background``) still runs XLA, through
``os._exit`` after flushing, since tearing the interpreter down under it aborts the process.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import signal
import stat
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

from jaxtraffic.io.files import atomic_write_bytes

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
MARKER = ".jaxtraffic-report"  # in every published report: this folder is evaluate.py's to replace
STAGING_MARKER = ".jaxtraffic-staging"  # in every staging folder: recognised as ours when stale
_PARTIAL = ".jaxtraffic-partial-"


class Stopped(BaseException):
    """A signal asked the job to stop; ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum, self.exit_code = signum, 128 + signum


def _raise(signum, frame):
    raise Stopped(signum)


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """While active (main thread only), SIGINT/SIGTERM/SIGHUP raise ``Stopped``; the previous handlers
    are restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, _raise) for sig in SIGNALS}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _is_ours(path: Path, marker: str) -> bool:
    """``path`` is a real folder (not a link) of this user holding ``marker`` as a regular file of this user."""
    try:
        st, mk = path.lstat(), (path / marker).lstat()
    except OSError:
        return False
    uid = os.getuid()
    return stat.S_ISDIR(st.st_mode) and stat.S_ISREG(mk.st_mode) and st.st_uid == uid and mk.st_uid == uid


def check_out(out: Path) -> str | None:
    """Why ``out`` may not be ``evaluate.py``'s output folder, or None when it may (see the module docstring)."""
    if str(out) == "":
        return "an empty path; name a folder (default results/)"
    if out.is_symlink() and not out.exists():
        return f"a dangling symbolic link (to {os.readlink(out)})"
    if out.exists() and not out.is_dir():
        return "exists and is not a directory"
    if out.is_dir():
        entries = [p.name for p in out.iterdir()]
        if entries and MARKER not in entries:
            return (f"a non-empty folder that holds no report of evaluate.py's (no {MARKER} file); it will not "
                    "write into it (it would replace entries of the same names): give a new or an empty folder")
        if entries and not (out / MARKER).is_file():
            return f"its {MARKER} is not a regular file"
    parent = out
    while not parent.exists() and not parent.is_symlink():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        return f"{parent} is not a writable directory"
    return None


def _lock(out: Path) -> int:
    """An exclusive lock on ``out``'s lock file (never following a link); ``ValueError`` if another job holds it."""
    lock = out.parent / f".{out.name}.jaxtraffic-lock"
    fd = os.open(lock, os.O_RDONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError(f"--out {out}: its lock {lock} is not a regular file")
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise ValueError(f"--out {out}: another evaluate.py is writing there (it holds {lock}); "
                         "wait for it or choose another --out") from None
    except BaseException:
        os.close(fd)
        raise
    return fd


class Staging:
    """The staging folder of one job writing ``out`` (see the module docstring); ``work`` is where to write."""

    def __init__(self, out: Path):
        self.out = Path(os.path.realpath(out)) if Path(out).is_symlink() else Path(out)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self._fd = _lock(self.out)
        try:
            for old in self.out.parent.glob(f".{self.out.name}{_PARTIAL}*"):
                if _is_ours(old, STAGING_MARKER):  # the lock proves no live job writes there
                    shutil.rmtree(old)
            self.work = Path(tempfile.mkdtemp(prefix=f".{self.out.name}{_PARTIAL}", dir=self.out.parent))
            (self.work / STAGING_MARKER).write_text(f"{os.getpid()}\n")
        except BaseException:
            os.close(self._fd)
            raise

    def publish(self) -> None:
        """Move the report into ``out`` (see the module docstring) and release the lock."""
        (self.work / STAGING_MARKER).unlink()
        (self.work / MARKER).write_text("a report written by evaluate.py; evaluate.py --out may replace it\n")
        with _deferred_signals() as got:
            _swap(self.work, self.out)
        self.close()
        if got:  # the move is a few renames: it was let finish, and the job is complete
            print(f"note: {signal.Signals(got[0]).name} received while the report was moved into {self.out}; "
                  "the move was completed first", file=sys.stderr, flush=True)

    def discard(self) -> None:
        shutil.rmtree(self.work, ignore_errors=True)
        self.close()

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


@contextlib.contextmanager
def _deferred_signals() -> Iterator[list[int]]:
    """While active (main thread only), SIGINT/SIGTERM/SIGHUP are recorded in the yielded list instead of acting
    (Python runs signal handlers in the main thread, whichever thread the signal reaches)."""
    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return
    old = {sig: signal.signal(sig, lambda signum, frame: got.append(signum)) for sig in SIGNALS}
    try:
        yield got
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _swap(work: Path, out: Path) -> None:
    """Replace ``out``'s entries by ``work``'s of the same names, all or none; removes ``work``. An entry of the
    same name is replaced only in a folder that holds a report of ours (its ``MARKER``): ``check_out`` judged
    ``out`` when the job started, and this judges it again, since the job ran for minutes meanwhile."""
    created = not out.exists()
    if created:
        out.mkdir()
    names = sorted(p.name for p in work.iterdir())
    clash = [n for n in names if n != MARKER and os.path.lexists(out / n)]
    if clash and not _is_ours(out, MARKER):  # placed there during the run, in a folder that holds no report of ours
        raise ValueError(f"--out {out}: {', '.join(clash)} appeared there during the run, in a folder that holds no "
                         f"report of evaluate.py's (no {MARKER}); nothing was replaced or removed")
    backup = Path(tempfile.mkdtemp(prefix=".jaxtraffic-old-", dir=out))
    moved_old, moved_new = [], []
    try:
        for name in names:
            if os.path.lexists(out / name):
                os.rename(out / name, backup / name)
                moved_old.append(name)
        for name in names:
            os.rename(work / name, out / name)
            moved_new.append(name)
    except BaseException:
        for name in moved_new:
            os.rename(out / name, work / name)
        for name in moved_old:
            os.rename(backup / name, out / name)
        backup.rmdir()
        if created:
            out.rmdir()
        raise
    work.rmdir()
    for name in moved_old:  # the previous report's entries: a link is removed, never followed
        p = backup / name
        shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
    backup.rmdir()


def copy_regular(src: Path, dst: Path) -> str:
    """Copy ``src`` to ``dst`` (atomically) if it is a regular file, never following a symbolic link, with
    permission bits no wider than ``src``'s (a 0600 file stays 0600): "copied", "link", "missing" or "other"."""
    try:
        fd = os.open(src, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        return "missing"
    except OSError as err:
        if err.errno == errno.ELOOP:
            return "link"
        raise
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            return "other"
        data = f.read()
    atomic_write_bytes(dst, data)
    os.chmod(dst, stat.S_IMODE(st.st_mode) & os.stat(dst).st_mode & 0o666)
    return "copied"


def leave(code: int) -> SystemExit:
    """``SystemExit(code)``, or an immediate exit if a background thread of the evaluation still runs."""
    if any(t.is_alive() and t.name.startswith("jaxtraffic-") for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return SystemExit(code)
