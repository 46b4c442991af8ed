"""Stopping a training run cleanly: SIGINT / SIGTERM become a flag checked between chunks.

Shared by the PPO trainer (``learn.trainer``) and the gradient trainer (``learn.gradient_trainer``):
``StopSignals`` turns the signals into a flag, ``report_interruption`` says what is on disk, and
``TrainingInterrupted`` carries the exit code (128 + the signal number) to ``train.py``.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["StopSignals", "TrainingInterrupted", "report_interruption"]


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by SIGINT/SIGTERM (or a KeyboardInterrupt) after saving what it could;
    ``exit_code`` is 128 + the signal number (130 for SIGINT, 143 for SIGTERM)."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum, self.exit_code, self.message = signum, 128 + signum, message


class StopSignals:
    """While active (main thread only), SIGINT and SIGTERM set ``signum`` instead of raising inside
    XLA; a second one exits at once (exit 128 + signal, nothing more is written). The previous
    handlers are restored on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, say):
        self.signum: int | None = None
        self.say, self.old = say, {}

    def _handle(self, signum, frame):
        if self.signum is not None:
            print(f"\n{signal.Signals(signum).name} again: exiting now without saving", file=sys.stderr, flush=True)
            os._exit(128 + signum)
        self.signum = signum
        print(f"\n{signal.Signals(signum).name} received: stopping after the current chunk (send it again to "
              "quit without saving)", file=sys.stderr, flush=True)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self.old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        for sig, handler in self.old.items():
            signal.signal(sig, handler)
        return False


def report_interruption(signum: int, run_dir: Path, any_chunk: bool, new_chunk: bool, progress: str) -> str:
    """Say what an interruption left on disk and return the message; raise ``TrainingInterrupted``
    if it left nothing new (otherwise the caller writes its summary first, then raises it)."""
    name = signal.Signals(signum).name
    if not any_chunk:
        msg = (f"interrupted ({name}) before the first chunk completed: no checkpoint exists yet (only config.json "
               f"in {run_dir}); run again without --resume")
    elif not new_chunk:
        msg = (f"interrupted ({name}) before a new chunk completed: the checkpoint at {progress} in {run_dir} is "
               "unchanged; continue with --resume")
    else:
        msg = (f"interrupted ({name}): the checkpoint of the last completed chunk ({progress}) is saved in "
               f"{run_dir}; continue with --resume")
    print(msg, file=sys.stderr, flush=True)
    if not any_chunk or not new_chunk:
        raise TrainingInterrupted(signum, msg)
    return msg
