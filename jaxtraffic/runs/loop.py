"""The one host training loop every algorithm runs (PPO, gradient-based, CEM).

``run_training(config, make_algorithm)`` owns what a run does around the compiled work, the same for every
algorithm: the run directory (checked, claimed, locked; ``session``), resume (the saved config with the new
run-control fields, its problem checked), config.json, printing (process 0 only), SIGINT/SIGTERM/SIGHUP
(``session.StopSignals``: a flag, acted on after the chunk in progress, agreed across processes), the
wall-clock budget, the learning curve (``curve``: the CSV appended a row per chunk, the figure at the end),
callbacks and TensorBoard, the checkpoint (after a session's first chunk, every ``checkpoint_every``-th, at
the end and on an interruption), the summary (with provenance) and ``TrainingInterrupted``.

An algorithm (``Algorithm``) supplies the rest: its opening line, one chunk (train, check, evaluate, and
the chunk's learning-curve row, progress line and milestones), its checkpoint and its summary. Progress is a
typed record (``Progress``), saved in the checkpoint as the same keys the checkpoints have always held.
"""

from __future__ import annotations

import copy
import math
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from jaxtraffic.io.files import write_json
from jaxtraffic.io.provenance import provenance
from jaxtraffic.platform import distributed
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, load_config
from jaxtraffic.runs.config.toml import CONFIG_TOML, config_toml, write_config
from jaxtraffic.runs.config.tree import run_control
from jaxtraffic.runs.curve import append_curve, plot_learning_curve, write_curve
from jaxtraffic.runs.session import (
    StopSignals,
    TrainingInterrupted,
    agree_stop,
    check_out_dir,
    check_resumable,
    claim_run_dir,
    finish_together,
    own_run_dir,
    print_or_drop,
    report_interruption,
)
from jaxtraffic.runs.tracking import MLflowTracker, TensorBoardWriter, as_callback, board_dir, run_name

__all__ = ["Algorithm", "Clock", "Progress", "run_training"]

CURVE = "learning_curve.csv"
_PLAIN = ("env_steps", "updates", "wall_s", "rows", "stopped")


@dataclass
class Progress:
    """How far a run has got: ``env_steps`` (environment steps, all environments), ``updates`` (compiled-program
    updates: PPO updates, Adam steps or CEM generations), ``wall_s`` (s, all sessions), the learning-curve
    ``rows``, whether the stop rule ``stopped`` the run, ``firsts`` (milestone name -> (wall s, count in
    ``counter``) when it first held) and ``own`` (the algorithm's own bookkeeping, saved as is)."""

    counter: str  # "env_steps" or "updates": the unit of the run's length and of its milestones
    milestones: tuple[str, ...] = ()  # the milestones the algorithm marks (recorded as null until reached)
    env_steps: int = 0
    updates: int = 0
    wall_s: float = 0.0
    rows: list[dict] = field(default_factory=list)
    stopped: bool = False
    firsts: dict[str, tuple[float, int]] = field(default_factory=dict)
    own: dict[str, Any] = field(default_factory=dict)

    @property
    def count(self) -> int:
        """The run's length so far, in its ``counter``."""
        return getattr(self, self.counter)

    def mark(self, milestone: str, hit: bool) -> None:
        """Record the first time ``milestone`` held (``hit``), at the current wall time and count."""
        if hit and milestone not in self.firsts:
            self.firsts[milestone] = (self.wall_s, self.count)

    def seconds_to(self, milestone: str) -> float | None:
        """Wall seconds at which ``milestone`` first held, None if never."""
        return self.firsts[milestone][0] if milestone in self.firsts else None

    def milestone_fields(self) -> dict[str, Any]:
        """``seconds_to_<m>`` and ``<counter>_to_<m>`` for every milestone (None: not reached), as saved."""
        out: dict[str, Any] = {}
        for m in dict.fromkeys((*self.milestones, *self.firsts)):
            sec, count = self.firsts.get(m, (None, None))
            out[f"seconds_to_{m}"], out[f"{self.counter}_to_{m}"] = sec, count
        return out

    def to_meta(self) -> dict[str, Any]:
        """The checkpoint's progress dict."""
        return {**{k: copy.deepcopy(getattr(self, k)) for k in _PLAIN}, **self.milestone_fields(),
                **copy.deepcopy(self.own)}

    @classmethod
    def from_meta(cls, meta: dict[str, Any], counter: str, milestones: tuple[str, ...] = ()) -> Progress:
        """Progress read back from a checkpoint's dict (``to_meta``)."""
        prog = cls(counter=counter, milestones=milestones, **{k: meta[k] for k in _PLAIN if k in meta})
        prefix = f"{counter}_to_"
        for key, value in meta.items():
            if key.startswith("seconds_to_") and value is not None:
                name = key.removeprefix("seconds_to_")
                prog.firsts[name] = (float(value), int(meta.get(prefix + name) or 0))
        prog.own = {k: v for k, v in meta.items()
                    if k not in (*_PLAIN, ckpt.PROBLEM) and not k.startswith(("seconds_to_", prefix))}
        return prog


class Clock:
    """Wall time of a run across its sessions and the rate of this session (from the end of its first chunk,
    so compilation is excluded)."""

    def __init__(self, wall0: float) -> None:
        self.wall0, self.t0 = wall0, time.perf_counter()
        self._from: tuple[float, int] | None = None

    def wall(self) -> float:
        """Seconds of the run so far (earlier sessions included)."""
        return self.wall0 + time.perf_counter() - self.t0

    def rate(self, count: int) -> float:
        """Count per second since this session's first chunk (NaN at the first chunk)."""
        now = time.perf_counter()
        if self._from is None:
            self._from = (now, count)
            return math.nan
        return (count - self._from[1]) / max(1e-9, now - self._from[0])


class Algorithm(Protocol):
    """One algorithm's part of a training run (``run_training`` does the rest)."""

    progress: Progress  # set by ``start``
    total: int  # the run ends when ``progress.count`` reaches it
    checkpoint_every: int  # chunks between checkpoints (and a session's first)
    curve_fields: list[str]
    curve_title: str | None
    unit: str  # the progress unit in messages, e.g. "env steps"

    def start(self, saved: tuple[Any, dict] | None, say: Callable[..., None]) -> str:
        """Initialise (from ``saved`` = (state dict, meta) on resume); return the opening line."""
        ...

    def chunk(self, clock: Clock) -> tuple[dict, str]:
        """Run one compiled chunk and evaluate it; update ``progress`` (counts, wall time, row, milestones,
        stop); return (the learning-curve row, the progress line)."""
        ...

    def snapshot(self) -> Any:
        """The state to checkpoint now (what ``save`` takes)."""
        ...

    def save(self, state: Any, meta: dict, run_dir: Path, writer: bool) -> None:
        """Write the checkpoint (a collective: every process calls it; the writer writes)."""
        ...

    def saved_best(self, run_dir: Path, writer: bool) -> None:
        """Write what is kept between checkpoints (PPO's best checkpoints) if it changed."""
        ...

    def finish(self, interrupted: bool, run_dir: Path, writer: bool) -> str:
        """Write summary.json (the writer; ``summary_base`` and the algorithm's fields); return the closing
        line."""
        ...


def _resumed_config(config: TrainConfig, run_dir: Path) -> TrainConfig:
    """The run's saved config, with only the run-control fields (``tree.run_control``) taken from ``config``."""
    own = config.tables()
    return load_config(run_dir).updated(**{s: {k: own[s][k] for k in names}
                                           for s, names in run_control(config.run.algo).items()})


def prepare(config: TrainConfig) -> tuple[TrainConfig, Path, tuple[Any, dict] | None]:
    """(the config to train, its run directory, the saved (state, meta) on resume): the run directory checked
    and claimed, the checkpoint read and checked against the config before anything compiles."""
    run_dir = Path(config.run.out_dir)
    check_out_dir(run_dir)
    saved = None
    if config.run.resume:
        check_resumable(run_dir)
        config = _resumed_config(config, run_dir)
    claim_run_dir(run_dir, config.run.resume, config.run.overwrite)  # refuse another run's directory first
    if config.run.resume:
        saved = ckpt.load_checkpoint(run_dir)
        ckpt.check_problem(config, saved[1].get(ckpt.PROBLEM), run_dir / ckpt.CHECKPOINT)
    return config, run_dir, saved


def run_training(config: TrainConfig, run_dir: Path, saved: tuple[Any, dict] | None,
                 make_algorithm: Callable[[], Algorithm], config_file: Callable[[], dict],
                 callbacks: Sequence[Callable[[dict], None]] = (), name: str = "jaxtraffic.train") -> Path:
    """Train (or resume) with the algorithm ``make_algorithm()`` builds and return the run directory; raises
    ``TrainingInterrupted`` after a signal (the checkpoint of the last completed chunk is on disk).

    ``config``, ``run_dir``, ``saved``: from ``prepare``. ``config_file()``: config.json's content.
    ``callbacks``: each learning-curve row (a dict) as soon as its chunk is evaluated (a ``tracking.Tracker``:
    ``tracking.as_callback``); ``run.tensorboard`` adds a ``TensorBoardWriter`` (in the run's own folder, the
    config as text) and ``run.mlflow`` an ``MLflowTracker`` (the config's fields as parameters), closed at the end."""
    writer = distributed.is_writer()  # process 0 prints and writes; the others only compute
    # (a closed stdout stops the printing only: print_or_drop)
    say = (lambda *a: None) if config.run.quiet or not writer else print_or_drop
    # (on resume: the steps logged after the checkpoint by the interrupted session are dropped, not drawn twice)
    purge = int(saved[1]["env_steps"]) + 1 if saved is not None else None
    owned = _trackers(config, run_dir, purge) if writer else []
    try:
        with own_run_dir(run_dir, config.run.resume, config.run.overwrite, writer, say), finish_together(name), \
                StopSignals(say) as stop:
            return _loop(config, run_dir, saved, make_algorithm, config_file,
                         [*callbacks, *map(as_callback, owned)], say, stop, writer)
    finally:
        for board in owned:
            board.close()


def _trackers(config: TrainConfig, run_dir: Path, purge: int | None) -> list:
    """The trackers ``config.run`` asks for (``run.tensorboard``, ``run.mlflow``), opened."""
    owned: list = []
    if config.run.tensorboard:
        owned.append(TensorBoardWriter(board_dir(config.run.tensorboard, run_dir, config.run.resume), purge,
                                       config_toml(config)))
    if config.run.mlflow:
        owned.append(MLflowTracker(config.run.mlflow, run_name=run_name(run_dir), params=config.tables()))
    return owned


def _loop(config: TrainConfig, run_dir: Path, saved, make_algorithm, config_file, callbacks: list, say,
          stop: StopSignals, writer: bool) -> Path:
    say("compiling (Ctrl-C or SIGTERM from now on stops at the next safe point) ...")
    algo = make_algorithm()
    opening = algo.start(saved, say)
    prog = algo.progress
    if saved is not None:
        say(f"resumed {run_dir} at {prog.count} {algo.unit} ({prog.wall_s:.1f} s)")
    if writer:  # (on resume: the run-control values this session was given, recorded)
        write_json(run_dir / ckpt.CONFIG, config_file())
        write_config(config, run_dir / CONFIG_TOML)  # python train.py --config run_dir/config.toml: this run again
        write_curve(run_dir / CURVE, prog.rows, algo.curve_fields)  # header (+ the saved rows) once
    say(opening)
    clock = Clock(float(prog.wall_s))
    at_start = saved_at = prog.count
    rows_at_start = len(prog.rows)
    consistent = None
    signum = agree_stop(False, False, stop)[2]
    try:
        while prog.count < algo.total and not prog.stopped and signum is None:
            row, line = algo.chunk(clock)
            say(line)
            # the state after this chunk, complete: saved now (a session's first chunk, every checkpoint_every-th)
            # or, if the loop ends before the next save, on the way out
            consistent = (algo.snapshot(), _meta(prog, config))
            chunks = len(prog.rows) - rows_at_start  # this session's, >= 1
            if chunks == 1 or chunks % algo.checkpoint_every == 0:
                algo.save(*consistent, run_dir, writer)
                saved_at = prog.count
            else:
                algo.saved_best(run_dir, writer)
            if writer:
                append_curve(run_dir / CURVE, row, algo.curve_fields)
                for callback in callbacks:
                    callback(row)
            prog.stopped, over_budget, signum = agree_stop(prog.stopped, prog.wall_s > config.run.max_wall_s, stop)
            if over_budget:
                say(f"stopping: wall-clock budget {config.run.max_wall_s:g} s reached")
                break
    except KeyboardInterrupt:  # raised by Python code (StopSignals turns signals into a flag)
        signum = signal.SIGINT
    interrupted = signum is not None
    msg = ""
    if interrupted and consistent is not None and consistent[1][prog.counter] != saved_at:
        algo.save(*consistent, run_dir, writer)  # the last completed chunk, before saying it is saved
    if signum is not None:  # (interrupted; spelled so that mypy narrows signum)
        msg = report_interruption(signum, run_dir, bool(prog.rows), prog.count != at_start,
                                  f"{prog.count} {algo.unit}")
    if not prog.rows:
        return run_dir
    if not interrupted:
        algo.save(algo.snapshot(), _meta(prog, config), run_dir, writer)
    if writer:
        plot_learning_curve(run_dir / CURVE, run_dir / "learning_curve.png", **(
            {"title": algo.curve_title} if algo.curve_title else {}))
    say(algo.finish(interrupted, run_dir, writer))
    if signum is not None:
        raise TrainingInterrupted(signum, msg)
    return run_dir


def _meta(prog: Progress, config: TrainConfig) -> dict:
    return {**prog.to_meta(), ckpt.PROBLEM: ckpt.problem_of(config)}


def summary_base(prog: Progress, interrupted: bool, eval_horizon_s: float) -> dict[str, Any]:
    """The summary fields every run has: provenance, counts, wall time, milestones, interruption."""
    return {"provenance": provenance(), "env_steps": prog.env_steps, "wall_s": prog.wall_s,
            **prog.milestone_fields(), "interrupted": interrupted, "eval_horizon_s": eval_horizon_s}

