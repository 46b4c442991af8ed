"""``evaluate.py``'s outputs made whole or not at all, only where the job may write, and its signals handled
like the trainers'.

``--out`` must be a folder the job owns (``check_out``): one that does not exist yet, an empty folder, or a
folder holding a report ``evaluate.py`` published there before. That is proved by its marker file, ``MARKER``: a
regular file (not a link) of this user, in JSON, naming the folder it was written for (its device and inode: a
copy of a report elsewhere, docs/results copied into a project, is not ours) and listing every file and folder the
report wrote. Anything else (a project folder, a home, a dangling symbolic link, ``""``, a marker of an older
version or of another folder) is refused before any work starts; nothing here ever removes a folder the job did not
write, nor an entry holding anything the listed report did not write.

``Staging(out)`` takes one lock per output folder (``.NAME.jaxtraffic-lock`` beside it, opened without following
a symbolic link: a second job on the same ``--out`` is refused), removes stale staging folders of earlier jobs on
the same ``--out`` (recognised by their own marker and their owner, while the lock proves no live job uses them),
and creates a fresh staging folder with ``tempfile.mkdtemp`` in the parent (mode 0700, an unpredictable name).
``publish()`` then moves each entry written there into ``out``, replacing the entry of the same name (entries of
``out`` the job did not write are left alone), with the signals deferred and every step undone if one fails:
``out`` ends up holding the new report or, unchanged, the previous one. If an entry to replace is not the previous
report's own (``Refused``), nothing is replaced and the new report stays in the staging folder, named in the error.
``discard()`` removes the staging folder.

``signals_raise()`` turns SIGINT, SIGTERM and SIGHUP into ``Stopped`` in the main thread (a
``BaseException``: no ``except Exception`` swallows it). ``leave(code)`` exits with ``code``; while one
of the evaluation's background threads (``paper.driver._Background``) still runs XLA, through
``os._exit`` after flushing, since tearing the interpreter down under it aborts the process.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
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


def stopped_in(err: BaseException) -> Stopped | None:
    """The ``Stopped`` that ``err`` is or was caused by, if any. A signal handled while a C extension runs Python
    code of its own (NumPy asking ml_dtypes for a dtype, say) can reach the caller as that extension's
    ``SystemError`` "returned a result with an exception set", the ``Stopped`` as its cause."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, Stopped):
            return err
        seen.add(id(err))
        err = err.__cause__ or err.__context__  # type: ignore[assignment]
    return None


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


_FORMAT = "jaxtraffic-report"
_MARKER_LIMIT = 1 << 22  # bytes: a report's marker lists a few hundred paths


class Refused(ValueError):
    """``publish`` found an entry to replace that the previous report did not write: nothing was replaced."""


def _listing(path: Path) -> list[str]:
    """Every path under ``path`` relative to it ("." for itself), a folder with a trailing "/", a link with "@":
    what a report wrote there (``MARKER``)."""
    def name(p: Path) -> str:
        rel = str(p.relative_to(path)) if p != path else "."
        return rel + ("@" if p.is_symlink() else "/" if p.is_dir() else "")

    if path.is_symlink() or not path.is_dir():
        return [name(path)]
    return sorted([name(path), *(name(p) for p in path.rglob("*"))])


def _folder_id(out: Path) -> list[int]:
    st = out.lstat()
    return [st.st_dev, st.st_ino]


def read_marker(out: Path) -> dict | str:
    """``out``'s ``MARKER`` (``{"entries": {name: listing}}``), or why ``out`` holds no report of ours."""
    try:
        fd = os.open(out / MARKER, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        return f"no {MARKER} file"
    except OSError as err:
        return f"its {MARKER} is a symbolic link" if err.errno == errno.ELOOP else f"its {MARKER}: {err.strerror}"
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid():
            return f"its {MARKER} is not a regular file of yours"
        data = f.read(_MARKER_LIMIT + 1)
    try:
        marker = json.loads(data) if len(data) <= _MARKER_LIMIT else None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        marker = None
    if not (isinstance(marker, dict) and marker.get("format") == _FORMAT and isinstance(marker.get("entries"), dict)):
        return f"its {MARKER} is not one evaluate.py writes (an older version's, or another file's)"
    if marker.get("folder") != _folder_id(out):
        return f"its {MARKER} was written for another folder (a copied report is not evaluate.py's to replace)"
    return marker


def check_out(out: Path) -> str | None:
    """Why ``out`` may not be ``evaluate.py``'s output folder, or None when it may (see the module docstring)."""
    if str(out) == "":
        return "an empty path; name a folder (default results/)"
    if out.is_symlink() and not out.exists():
        return f"a dangling symbolic link (to {os.readlink(out)})"
    if out.exists() and not out.is_dir():
        return "exists and is not a directory"
    if out.is_dir() and any(out.iterdir()):
        marker = read_marker(out)
        if isinstance(marker, str):
            return (f"a non-empty folder that holds no report of evaluate.py's ({marker}); it will not write into it "
                    "(it would replace entries of the same names): give a new or an empty folder")
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
        self.kept = False  # publish() refused: the report stays in work for the user
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
        """Move the report into ``out`` (see the module docstring) and release the lock; ``Refused`` (the new
        report kept in ``work``) if an entry to replace is not the previous report's."""
        (self.work / STAGING_MARKER).unlink()
        with _deferred_signals() as got:
            try:
                _swap(self.work, self.out)
            except Refused:
                self.kept = True  # discard() leaves it
                raise
        self.close()
        if got:  # the move is a few renames: it was let finish, and the job is complete
            print(f"note: {signal.Signals(got[0]).name} received while the report was moved into {self.out}; "
                  "the move was completed first", file=sys.stderr, flush=True)

    def discard(self) -> None:
        if not self.kept:
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
    same name is replaced only if the previous report's ``MARKER`` lists it and everything now under it (judged
    again here: the job ran for minutes since ``check_out``); otherwise ``Refused``, nothing touched."""
    created = not out.exists()
    if created:
        out.mkdir()
    names = sorted(p.name for p in work.iterdir())
    clash = [n for n in names if os.path.lexists(out / n) and n != MARKER]
    previous = read_marker(out) if any(p.name != MARKER for p in out.iterdir()) else {"entries": {}}
    if isinstance(previous, str):
        foreign = clash
    else:
        foreign = [n for n in clash if not set(_listing(out / n)) <= set(previous["entries"].get(n, ()))]
    if foreign:
        raise Refused(f"--out {out}: {', '.join(foreign)} hold(s) what no report of evaluate.py's wrote there "
                      f"({previous if isinstance(previous, str) else 'files added since'}); nothing was replaced or "
                      f"removed, and the new report is in {work}")
    kept = {} if isinstance(previous, str) else {n: v for n, v in previous["entries"].items()
                                                  if n not in names and os.path.lexists(out / n)}
    entries = {**kept, **{n: _listing(work / n) for n in names}}
    (work / MARKER).write_text(json.dumps({"format": _FORMAT, "version": 2, "folder": _folder_id(out),
                                           "entries": entries}, indent=1) + "\n")
    names = sorted(p.name for p in work.iterdir())
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
