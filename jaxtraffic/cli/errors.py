"""One line and one exit status for every way ``train.py`` and ``evaluate.py`` fail (``exit_codes(prog)``).

======================================================  ======  =============================================
failure                                                  status  what is printed (stderr, one line)
======================================================  ======  =============================================
invalid flags or input (``ValueError``; a missing file)  2       ``PROG: error: MESSAGE``
an OS error (no space, read-only, name too long, a       74      ``PROG: error: PATH: CAUSE`` (sysexits'
folder where a file belongs, no permission, ...)                 ``EX_IOERR``)
standard output closed (``PROG | head -1``)              74      ``PROG: error: standard output was closed``
a signal (SIGINT, SIGTERM, SIGHUP)                       128+N   said by the job (what is kept)
======================================================  ======  =============================================

A ``SystemExit`` raised inside (tyro's usage errors: 2) passes through unchanged. What the job writes is
written atomically (``jaxtraffic.io.files``) or staged (``cli.staging``), so a failure leaves nothing half-written.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from collections.abc import Iterator

USAGE, IOERR = 2, 74  # sysexits.h: EX_USAGE is 64, but argparse (and these programs since round one) use 2


def describe(err: OSError) -> str:
    """``PATH: CAUSE`` of an OS error (the second path of a rename too), else its message."""
    cause = err.strerror or (errno.errorcode.get(err.errno, "") if err.errno else "") or str(err)
    paths = [p for p in (err.filename, err.filename2) if p is not None]
    return f"{' -> '.join(os.fsdecode(p) for p in paths)}: {cause}" if paths else str(err) or type(err).__name__


def _say(prog: str, msg: str) -> None:
    try:
        print(f"{prog}: error: {msg}", file=sys.stderr, flush=True)
    except OSError:
        pass


def _quiet_stdout() -> None:
    """Point the closed standard output at /dev/null so that the interpreter's final flush says nothing."""
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def code_of(err: BaseException) -> int | None:
    """The exit status ``exit_codes`` gives ``err`` (None: not one of its classes)."""
    exit_code = getattr(err, "exit_code", None)
    if isinstance(exit_code, int):  # Stopped, TrainingInterrupted: 128 + the signal
        return exit_code
    if isinstance(err, (ValueError, FileNotFoundError, NotADirectoryError)):
        return USAGE
    if isinstance(err, OSError):
        return IOERR
    return None


def report(prog: str, err: BaseException) -> int | None:
    """Say ``err`` in one line (see the table above) and return its exit status; None (nothing said) when it is
    not one of the table's classes."""
    code = code_of(err)
    if code is None or isinstance(err, SystemExit):
        return None
    if isinstance(err, BrokenPipeError):
        _quiet_stdout()
        _say(prog, "standard output was closed (broken pipe); stopped")
    elif getattr(err, "exit_code", None) is None:  # a signal: the job has said what it kept
        _say(prog, describe(err) if isinstance(err, OSError) else str(err))
    return code


@contextlib.contextmanager
def interrupt_is_130(prog: str) -> Iterator[None]:
    """Ctrl-C before the job starts (parsing the flags, checking the paths: nothing to save yet): one line and
    exit status 130, no traceback."""
    try:
        yield
    except KeyboardInterrupt:
        _say(prog, "interrupted (Ctrl-C) before the job started; nothing was written")
        raise SystemExit(130) from None


@contextlib.contextmanager
def exit_codes(prog: str) -> Iterator[None]:
    """Turn the failures of the table above into one line on stderr and ``SystemExit(status)``."""
    try:
        yield
    except SystemExit:
        raise
    except BaseException as err:
        code = report(prog, err)
        if code is None:
            raise
        raise SystemExit(code) from None
