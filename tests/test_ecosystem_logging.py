"""Training logging: the callback hook, the appended learning_curve.csv, the progress
line's rate excluding compilation, and the optional TensorBoard writer (when tensorboardX is
installed). One tiny run (21 nodes, 4 environments x 8 steps, 3 chunks)."""

from __future__ import annotations

import csv
import time

import pytest
from extras import available, need

from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.curve import CURVE_FIELDS
from jaxtraffic.runs.ppo.trainer import train

TINY = {"n_points": 21, "delay": 0.5, "max_delay_steps": 20, "num_envs": 4, "num_steps": 8, "updates_per_chunk": 2,
        "update_epochs": 2, "num_minibatches": 2, "horizon_s": 3.0, "eval_horizon_s": 2.0, "val_horizon_s": 2.0,
        "keep_going": True}
CHUNK = 4 * 8 * 2


@pytest.mark.slow
def test_callbacks_csv_progress_and_tensorboard(tmp_path, capsys):
    has_tb = available("tensorboardX")
    seen: list[dict] = []
    cfg = TrainConfig.from_flat(**TINY, total_steps=3 * CHUNK, out_dir=str(tmp_path / "run"),
                                tensorboard=str(tmp_path / "tb") if has_tb else None)
    run = train(cfg, callbacks=[seen.append])
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("[")]
    text = (run / "learning_curve.csv").read_text()
    assert text.count("update,env_steps") == 1  # the header is written once, the rows are appended
    with open(run / "learning_curve.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["env_steps"]) for r in rows] == [int(r["env_steps"]) for r in seen] == [CHUNK, 2 * CHUNK, 3 * CHUNK]
    for r, s in zip(rows, seen, strict=True):
        assert set(CURVE_FIELDS) <= set(s)
        assert float(r["eval_reward"]) == pytest.approx(s["eval_reward"], rel=1e-12)
    # the first chunk compiles: no rate or ETA; later ones measure from the end of the first
    assert len(lines) == 3 and "? steps/s" in lines[0] and "ETA ?" in lines[0]
    assert "? steps/s" not in lines[1] and "ETA ?" not in lines[1]
    if has_tb:
        events = list((tmp_path / "tb").glob("events.out.tfevents.*"))
        assert events and events[0].stat().st_size > 0


def test_tensorboard_without_tensorboardx_is_a_clear_error(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_tbx(name, *args, **kwargs):
        if name.startswith("tensorboardX"):
            raise ImportError("no tensorboardX")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_tbx)
    from jaxtraffic.runs.tensorboard import TensorBoardWriter

    with pytest.raises(ValueError, match=r"jaxtraffic\[tb\]"):
        TensorBoardWriter(tmp_path / "tb")


def test_tensorboard_drops_the_steps_a_resume_logs_again(tmp_path):
    """An interrupted session logged up to 3 chunks, its checkpoint holds 1: the resumed session's rows replace
    chunks 2 and 3 (read back as TensorBoard reads them), none is drawn twice."""
    need("tensorboardX")
    accumulator = need("tensorboard.backend.event_processing.event_accumulator")
    from jaxtraffic.runs.tensorboard import TensorBoardWriter

    first = TensorBoardWriter(tmp_path)
    for k in (1, 2, 3):
        first({"env_steps": k * CHUNK, "eval_reward": -float(k)})
    first.close()
    time.sleep(1.1)  # (event file names hold the second: the resumed session's file sorts after)
    resumed = TensorBoardWriter(tmp_path, purge_step=CHUNK + 1)  # what run_training passes: checkpoint + 1
    for k in (2, 3):
        resumed({"env_steps": k * CHUNK, "eval_reward": 10.0 * k})
    resumed.close()
    acc = accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    got = [(e.step, e.value) for e in acc.Scalars("train/eval_reward")]
    assert got == [(CHUNK, -1.0), (2 * CHUNK, 20.0), (3 * CHUNK, 30.0)]
