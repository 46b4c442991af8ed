"""``evaluate.py``'s outputs made whole or not at all, and its signals handled like the trainers'.

``staging_dir(out)`` gives a hidden sibling directory (``.NAME.partial-PID``) to write into; when the job ends
normally each entry written there replaces the entry of the same name in ``out`` at once (files by
``os.replace``, directories by a rename), so ``out`` never holds a half-written report beside an older
one (``publish``); entries of ``out`` this job did not write are left alone. On an error or a signal the staging
directory is removed (``discard``) and ``out`` is unchanged.

``signals_raise()`` turns SIGINT, SIGTERM and SIGHUP into ``Stopped`` in the main thread (a
``BaseException``: no ``except Exception`` swallows it). ``leave(code)`` exits with ``code``; while one
of the evaluation's background threads (``paper.driver._Background``) still runs XLA, through
``os._exit`` after flushing, since tearing the interpreter down under it aborts the process.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


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


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def staging_dir(out: Path) -> Path:
    """The hidden sibling of ``out`` this process writes into; stale ones of dead processes are removed."""
    out = Path(out)
    for old in out.parent.glob(f".{out.name}.partial-*") if out.parent.is_dir() else ():
        pid = old.name.rsplit("-", 1)[-1]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return out.parent / f".{out.name}.partial-{os.getpid()}"


def publish(work: Path, out: Path) -> None:
    """Move every entry of ``work`` into ``out`` (replacing those of the same name) and remove ``work``."""
    out.mkdir(parents=True, exist_ok=True)
    for entry in sorted(work.iterdir()):
        target = out / entry.name
        if entry.is_dir() and not entry.is_symlink():
            old = None
            if target.exists() or target.is_symlink():
                old = out / f".{entry.name}.old-{os.getpid()}"
                target.rename(old)
            entry.rename(target)
            if old is not None:
                shutil.rmtree(old) if old.is_dir() and not old.is_symlink() else old.unlink()
        else:
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(entry, target)
    work.rmdir()


def discard(work: Path | None) -> None:
    if work is not None:
        shutil.rmtree(work, ignore_errors=True)


def leave(code: int) -> SystemExit:
    """``SystemExit(code)``, or an immediate exit if a background thread of the evaluation still runs."""
    if any(t.is_alive() and t.name.startswith("jaxtraffic-") for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return SystemExit(code)
