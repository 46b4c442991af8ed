"""Run-directory checks and interruption handling shared by the PPO and gradient trainers.

``StopSignals`` turns SIGINT / SIGTERM into a flag checked between chunks; ``TrainingInterrupted``
is raised after what could be saved was saved (``exit_code`` 130 / 143); ``check_out_dir``,
``check_resumable`` and ``open_run_dir`` give clear errors for unusable run directories; ``RunLock`` and
``claim_run_dir`` make a run directory belong to one run (a lock while training; a fresh run refuses a
directory holding another run's results unless told to clear it); ``check_finite`` stops a training whose
parameters or loss went NaN/inf (``NonFiniteTraining``) before anything of that chunk is written.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import signal
import stat
import sys
import threading
from pathlib import Path

import jax
import numpy as np

from jaxtraffic.io.files import atomic_write_bytes, clean_stale_tmp
from jaxtraffic.platform import distributed
from jaxtraffic.runs import checkpoint as ckpt

__all__ = ["NonFiniteTraining", "RunLock", "StopSignals", "TrainingInterrupted", "check_finite", "check_out_dir",
           "check_resumable", "claim_run_dir", "fmt_time", "is_run_dir", "open_run_dir", "own_run_dir", "print_or_drop",
           "report_interruption"]

LOCK = ".lock"  # held (flock) by the training that writes the directory
# what a run writes: a fresh run in a directory holding any of them would mix two runs
RUN_FILES = (ckpt.CONFIG, "config.toml", ckpt.CHECKPOINT, ckpt.BEST, ckpt.SUMMARY, "learning_curve.csv",
             "learning_curve.png")
RESULTS = (ckpt.CHECKPOINT, ckpt.BEST, ckpt.SUMMARY)  # what a fresh run would mix with
# written first into every run directory: the proof that the folder is a training run's (claim_run_dir)
RUN_MARKER = ".jaxtraffic-run"
_MARKER_TEXT = b"jaxtraffic training run: train.py may replace the files it wrote here (--resume, --overwrite)\n"


def print_or_drop(*args, file=None) -> None:
    """``print(*args, file=file, flush=True)``; a closed stream (a pipe whose reader went: ``train.py | head``,
    Ctrl-C under ``| tee``, which kills the reader first) stops that stream's output only: it is pointed at
    /dev/null from then on (its file descriptor too, so that the exit's flush cannot fail) and the training goes
    on to its checkpoint and summary."""
    stream = sys.stdout if file is None else file
    try:
        print(*args, file=stream, flush=True)
    except BrokenPipeError:  # (EPIPE: Python ignores SIGPIPE)
        os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())
        if stream is sys.stdout:  # said once, where it can still be read
            print_or_drop("standard output was closed (broken pipe): training goes on without printing; Ctrl-C "
                          "(SIGINT) or SIGTERM saves and stops as usual", file=sys.stderr)


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by SIGINT/SIGTERM (or a KeyboardInterrupt) after saving what it could;
    ``exit_code`` is 128 + the signal number (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum, self.exit_code, self.message = signum, 128 + signum, message


class StopSignals:
    """While active (main thread only), SIGINT, SIGTERM and SIGHUP set ``signum`` instead of raising inside
    XLA; a second one exits at once (exit 128 + signal, nothing more is written). The previous
    handlers are restored on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self, say):
        self.signum: int | None = None
        self.say, self.old = say, {}

    def _handle(self, signum, frame):
        if self.signum is not None:
            print_or_drop(f"\n{signal.Signals(signum).name} again: exiting now without saving", file=sys.stderr)
            os._exit(128 + signum)
        self.signum = signum
        print_or_drop(f"\n{signal.Signals(signum).name} received: stopping after the current chunk (send it again "
                      "to quit without saving)", file=sys.stderr)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self.old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        for sig, handler in self.old.items():
            signal.signal(sig, handler)
        return False


@contextlib.contextmanager
def finish_together(name: str):
    """Every process leaves the block together (``distributed.barrier(name)``) when it ends normally
    or by an agreed interruption (``TrainingInterrupted``), so that none returns before process 0's
    files are complete; any other error leaves at once."""
    try:
        yield
    except TrainingInterrupted:
        distributed.barrier(name)
        raise
    distributed.barrier(name)


def agree_stop(stopped: bool, over_budget: bool, stop: StopSignals) -> tuple[bool, bool, int | None]:
    """Process 0's stop and wall-budget decisions and the largest signal number any process received
    (None: none), the same on every process (a collective: every process calls it at the same point)."""
    votes = distributed.agree([stopped, over_budget, stop.signum or 0])
    return bool(votes[0, 0]), bool(votes[0, 1]), int(votes[:, 2].max()) or None


def check_out_dir(run_dir: Path) -> None:
    """``ValueError`` unless ``run_dir`` is (or can be created as) a writable directory."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"out_dir {run_dir}: exists and is not a directory")
    parent = run_dir
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"out_dir {run_dir}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"out_dir {run_dir}: {parent} is not writable")


def fmt_time(sec: float) -> str:
    """``sec`` seconds as ``<m>m<ss>s``; ``?`` when not finite."""
    if not math.isfinite(sec):
        return "?"
    m, s = divmod(int(sec), 60)
    return f"{m}m{s:02d}s"


def eta_text(remaining: float, rate: float) -> str:
    """The progress lines' ``ETA <m>m<ss>s``: ``remaining`` work at ``rate`` (work per second; NaN or 0 while
    unknown, e.g. at a first, compiling chunk: ``ETA ?``)."""
    return f"ETA {fmt_time(max(0.0, remaining) / rate if rate > 0 else math.nan)}"


def check_resumable(run_dir: Path) -> None:
    """``ValueError`` unless ``run_dir`` holds a config.json and a checkpoint to resume from."""
    if not (run_dir / ckpt.CHECKPOINT).exists():
        why = ("it has a config.json but no checkpoint: the run was stopped before its first chunk completed"
               if (run_dir / ckpt.CONFIG).exists() else "it is not a run directory (no config.json, no checkpoint)")
        raise ValueError(f"resume: nothing to resume in {run_dir}: {why}; run without resume to start afresh")
    if not (run_dir / ckpt.CONFIG).exists():
        raise ValueError(f"resume: {run_dir / ckpt.CONFIG} is missing (the checkpoint alone does not say how it "
                         "was trained)")


def check_total(meta: dict, counter: str, total: int, flag: str, path: Path) -> None:
    """On resume: ``ValueError`` if the run's new length ``total`` (``flag``) is below what the checkpoint at
    ``path`` has already done (its ``meta[counter]``): the run would record a length it has passed."""
    done = meta.get(counter) if isinstance(meta, dict) else None
    if isinstance(done, int) and total < done:
        raise ValueError(f"--resume: {path} has already done {done} {counter.replace('_', ' ')}; {flag} {total} is "
                         f"below that: give {flag} >= {done} to continue (or leave it out)")


def rounding_note(total: int, per_chunk: int, flag: str, unit: str, chunk: str) -> str:
    """The note a run says once at its start when its length ``total`` (``flag``, in ``unit``) is no whole number of
    chunks of ``per_chunk`` (``chunk``: what a chunk is made of): the run goes on to the end of the chunk that
    passes it; "" when it is a whole number."""
    if total % per_chunk == 0:
        return ""
    end = -(-total // per_chunk) * per_chunk
    return (f"note: {flag} {total} is rounded up to {end} {unit}: the run goes in whole chunks of {per_chunk} {unit} "
            f"({chunk}), and the last one ends past {total}")


def report_interruption(signum: int, run_dir: Path, any_chunk: bool, new_chunk: bool, progress: str) -> str:
    """Say what an interruption left on disk and return the message; raise ``TrainingInterrupted``
    if it left nothing new (otherwise the caller writes its summary first, then raises it)."""
    name = signal.Signals(signum).name
    if not any_chunk:
        msg = (f"interrupted ({name}) before the first chunk completed: no checkpoint exists yet (only config.json "
               f"in {run_dir}); run again without resume")
    elif not new_chunk:
        msg = (f"interrupted ({name}) before a new chunk completed: the checkpoint at {progress} in {run_dir} is "
               "unchanged; continue with resume")
    else:
        msg = (f"interrupted ({name}): the checkpoint of the last completed chunk ({progress}) is saved in "
               f"{run_dir}; continue with resume")
    print_or_drop(msg, file=sys.stderr)
    if not any_chunk or not new_chunk:
        raise TrainingInterrupted(signum, msg)
    return msg


def open_run_dir(run_dir: Path) -> None:
    """Create the run directory (clear error if impossible)."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"out_dir {run_dir}: cannot create it ({err.strerror})") from None


@contextlib.contextmanager
def own_run_dir(run_dir: Path, resume: bool, overwrite: bool, writer: bool, say):
    """The writing process's hold on the run directory for a training: created, locked (``RunLock``),
    another run's files cleared (a fresh run with ``overwrite``; ``claim_run_dir``) and temporary files of an
    interrupted write removed; the other processes of a multi-process run only compute."""
    if not writer:
        yield
        return
    open_run_dir(run_dir)
    with RunLock(run_dir):
        claim_run_dir(run_dir, resume, overwrite, clear=True)
        stale = clean_stale_tmp(run_dir, (*RUN_FILES, RUN_MARKER))
        if stale:
            say(f"removed {len(stale)} temporary file(s) left by an interrupted write: "
                f"{', '.join(p.name for p in stale)}")
        yield


class NonFiniteTraining(ValueError):
    """The parameters or the loss of a training went NaN/inf; nothing of that chunk was written."""


def check_finite(what: str, tree, run_dir: Path, progress: str) -> None:
    """``NonFiniteTraining`` unless every leaf of ``tree`` (parameters, losses) is finite."""
    bad = [jax.tree_util.keystr(path) for path, leaf in jax.tree_util.tree_leaves_with_path(jax.device_get(tree))
           if not np.all(np.isfinite(np.asarray(leaf, dtype=float)))]
    if bad:
        kept = (f"the last finite checkpoint ({progress}) is kept in {run_dir}" if (run_dir / ckpt.CHECKPOINT).exists()
                else f"no checkpoint was written to {run_dir}")
        raise NonFiniteTraining(f"training went non-finite: {what} {', '.join(bad[:4])}{' ...' if len(bad) > 4 else ''}"
                                f" became NaN/inf; {kept}. Lower the learning rate or the scales that blew up")


def _regular_head(path: Path, n: int) -> bytes:
    """The first ``n`` bytes of ``path`` if it is a regular file of this user (never following a link, never
    blocking on a FIFO), else ``b""``."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return b""
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        return f.read(n) if stat.S_ISREG(st.st_mode) and st.st_uid == os.getuid() else b""


def _marked(run_dir: Path) -> bool:
    return _regular_head(run_dir / RUN_MARKER, len(_MARKER_TEXT) + 1) == _MARKER_TEXT


def is_run_dir(run_dir: Path) -> bool:
    """``run_dir`` holds a training run of ours: its ``RUN_MARKER`` (a regular file of this user with the marker's
    exact text) or, for a run written before the marker existed, a checkpoint or best policy in the checksummed
    format (its header names ``ckpt.FORMAT``). Neither is held by a user's folder by accident."""
    return _marked(run_dir) or any(ckpt.FORMAT.encode() in _regular_head(run_dir / name, 64)
                                   for name in (ckpt.CHECKPOINT, ckpt.BEST))


def claim_run_dir(run_dir: Path, resume: bool, overwrite: bool, clear: bool = False) -> None:
    """A run directory holds one run, and is new, empty or a run of ours (``is_run_dir``): a folder holding
    anything else is refused (``ValueError``), with or without ``overwrite``, and nothing in it is touched. A
    fresh run refuses a directory holding another run's results unless ``overwrite``; with ``clear`` (the writer,
    under ``RunLock``) those files are removed first and the marker is written. A run of ours holding no results
    (a run stopped before its first chunk completed) is taken over without asking."""
    if not run_dir.is_dir():
        return
    ours = is_run_dir(run_dir)
    if not ours and any(p.name != LOCK for p in run_dir.iterdir()):
        raise ValueError(f"out_dir {run_dir}: a non-empty folder that holds no training run of jaxtraffic's (no "
                         f"{RUN_MARKER} file, no checkpoint); train.py writes only into a new, an empty or its own "
                         "run folder: give another out_dir")
    if resume:
        return
    present = [n for n in RUN_FILES if (run_dir / n).exists() or (run_dir / n).is_symlink()]
    if any(n in RESULTS for n in present) and not overwrite:
        raise ValueError(f"out_dir {run_dir}: holds a run already ({', '.join(present)}); continue it with "
                         "resume, or set overwrite to clear it and start afresh")
    if clear:
        for name in present:
            (run_dir / name).unlink()
        if not _marked(run_dir):
            atomic_write_bytes(run_dir / RUN_MARKER, _MARKER_TEXT)


class RunLock:
    """An exclusive lock on the run directory while a training writes it (``flock`` on ``.lock``: released
    when the process ends, however it ends). A second training of the same directory gets a ``ValueError``."""

    def __init__(self, run_dir: Path, active: bool = True):
        self.path, self.active = run_dir / LOCK, active
        self.fd: int | None = None

    def __enter__(self):
        if not self.active:
            return self
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise ValueError(f"out_dir {self.path.parent}: another training is writing to it (it holds "
                             f"{self.path.name}); wait for it to end or choose another out_dir") from None
        self.fd = fd
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None
        return False
