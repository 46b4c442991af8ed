"""The one host training loop (``learn.runs.loop``) with a stand-in algorithm (no JAX): what it owns whatever the
algorithm (checkpoints after a session's first chunk and every ``checkpoint_every``-th, the curve, callbacks,
the summary, an interruption), and the typed progress record's round trip through a checkpoint."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from jaxtraffic.io.files import write_json
from jaxtraffic.runs import checkpoint as ckpt
from jaxtraffic.runs.config import TrainConfig, config_json
from jaxtraffic.runs.loop import Progress, prepare, run_training
from jaxtraffic.runs.ppo.selection import BAD, UNVALIDATED, Validation, format_scores
from jaxtraffic.runs.session import TrainingInterrupted


class Counting:
    """A stand-in algorithm: its state is a number that each chunk adds one to; it stops at ``total`` chunks, or
    raises ``KeyboardInterrupt`` in chunk ``interrupt_at``."""

    unit = "updates"
    curve_fields = ["update", "env_steps", "wall_s", "eval_reward", "value"]
    curve_title = None

    def __init__(self, total: int, checkpoint_every: int, interrupt_at: int | None = None):
        self.total, self.checkpoint_every, self.interrupt_at = total, checkpoint_every, interrupt_at
        self.saves: list[int] = []
        self.finished: list[bool] = []

    def start(self, saved, say):
        self.progress = Progress("updates", ("half",))
        self.value = 0
        if saved is not None:
            self.value = int(saved[0]["value"])
            self.progress = Progress.from_meta(saved[1], "updates", ("half",))
        return "counting"

    def chunk(self, clock):
        if self.interrupt_at is not None and self.progress.updates + 1 == self.interrupt_at:
            raise KeyboardInterrupt
        self.value += 1
        prog = self.progress
        prog.updates += 1
        prog.wall_s = clock.wall()
        prog.mark("half", prog.updates * 2 >= self.total)
        row = {"update": prog.updates, "env_steps": 0, "wall_s": prog.wall_s, "eval_reward": -1.0 / self.value,
               "value": self.value}
        prog.rows.append(row)
        return row, f"update {prog.updates}"

    def snapshot(self):
        return {"value": self.value}

    def save(self, state, meta, run_dir: Path, writer: bool):
        self.saves.append(meta["updates"])
        ckpt.save_checkpoint(run_dir, state, meta)

    def saved_best(self, run_dir, writer):
        pass

    def finish(self, interrupted, run_dir: Path, writer: bool):
        self.finished.append(interrupted)
        write_json(run_dir / ckpt.SUMMARY, {"value": self.value, **self.progress.milestone_fields()})
        return "done"


def _run(tmp_path: Path, algo: Counting, **run):
    config = TrainConfig.make(run={"out_dir": str(tmp_path / "run"), "quiet": True, **run})
    config, run_dir, saved = prepare(config)
    rows: list[dict] = []
    run_training(config, run_dir, saved, lambda: algo, lambda: config_json(config), [rows.append])
    return run_dir, rows


def test_the_loop_checkpoints_curves_and_summarises_any_algorithm(tmp_path):
    algo = Counting(total=5, checkpoint_every=2)
    run_dir, rows = _run(tmp_path, algo)
    assert algo.saves == [1, 2, 4, 5]  # the first chunk, every second one, and the end
    assert [r["value"] for r in rows] == [1, 2, 3, 4, 5] and algo.finished == [False]
    with open(run_dir / "learning_curve.csv") as f:
        assert [int(r["value"]) for r in csv.DictReader(f)] == [1, 2, 3, 4, 5]
    state, meta = ckpt.load_checkpoint(run_dir)
    assert state["value"] == 5 and meta["updates"] == 5 and meta["updates_to_half"] == 3
    assert meta[ckpt.PROBLEM] == ckpt.problem_of(TrainConfig.make(run={"out_dir": str(run_dir), "quiet": True}))
    assert (run_dir / "learning_curve.png").exists() and (run_dir / ckpt.CONFIG).exists()


def test_an_interruption_keeps_the_last_completed_chunk_and_resume_continues_it(tmp_path):
    algo = Counting(total=5, checkpoint_every=10, interrupt_at=4)
    with pytest.raises(TrainingInterrupted):
        _run(tmp_path, algo)
    assert algo.saves == [1, 3] and algo.finished == [True]  # chunk 3 saved on the way out, before saying so
    resumed = Counting(total=5, checkpoint_every=10)
    run_dir, rows = _run(tmp_path, resumed, resume=True)
    assert [r["value"] for r in rows] == [4, 5] and resumed.saves == [4, 5]
    with open(run_dir / "learning_curve.csv") as f:
        assert [int(r["value"]) for r in csv.DictReader(f)] == [1, 2, 3, 4, 5]


def test_progress_round_trips_through_a_checkpoint_with_its_milestones_and_own_bookkeeping():
    prog = Progress("env_steps", ("stop_rule", "paper_rule"), env_steps=64, wall_s=2.5, rows=[{"a": 1}])
    prog.mark("paper_rule", True)
    prog.env_steps, prog.wall_s = 128, 4.0
    prog.mark("paper_rule", True)  # only the first time counts
    prog.own["restarts"] = [{"env_steps": 64, "members": [1]}]
    meta = prog.to_meta()
    assert meta["seconds_to_paper_rule"] == 2.5 and meta["env_steps_to_paper_rule"] == 64
    assert meta["seconds_to_stop_rule"] is None and meta["restarts"] == prog.own["restarts"]
    back = Progress.from_meta({**meta, ckpt.PROBLEM: "{}"}, "env_steps", ("stop_rule", "paper_rule"))
    assert back == prog


def test_a_score_says_whether_it_was_validated():
    assert Validation.of(0.7) is Validation.SCORED and Validation.of(BAD) is Validation.REJECTED
    assert Validation.of(UNVALIDATED - 0.5) is Validation.NOT_VALIDATED
    assert format_scores([0.5, BAD + 3, UNVALIDATED + 1]) == "0.50,bad,-"
    assert all(v.message for v in Validation)
