"""Training logging: the callback hook, the appended learning_curve.csv, the progress
line's rate excluding compilation, and the trackers behind one protocol (``runs.tracking``): TensorBoard (when
tensorboardX is installed) and MLflow's offline SQLite store (when mlflow is). One tiny run (21 nodes,
4 environments x 8 steps, 3 chunks)."""

from __future__ import annotations

import csv
import time

import pytest
from extras import available, need

from jaxtraffic.runs.config import TrainConfig
from jaxtraffic.runs.curve import CURVE_FIELDS
from jaxtraffic.runs.ppo.trainer import train
from jaxtraffic.runs.tracking import as_callback, scalars

TINY = {"plant": {"n_points": 21, "delay": 0.5, "max_delay_steps": 20},
        "ppo": {"num_envs": 4, "num_steps": 8, "updates_per_chunk": 2, "update_epochs": 2, "num_minibatches": 2},
        "env": {"horizon_s": 3.0}, "run": {"eval_horizon_s": 2.0, "val_horizon_s": 2.0, "keep_going": True}}
CHUNK = 4 * 8 * 2


@pytest.mark.slow
def test_callbacks_csv_progress_and_tensorboard(tmp_path, capsys):
    has_tb, has_mlflow = available("tensorboardX"), available("mlflow")
    seen: list[dict] = []
    cfg = TrainConfig.make(**TINY).updated(run={"total_steps": 3 * CHUNK, "out_dir": str(tmp_path / "run"),
                                                "tensorboard": str(tmp_path / "tb") if has_tb else None})
    trackers = []
    if has_mlflow:
        from jaxtraffic.runs.tracking import MLflowTracker

        trackers.append(MLflowTracker(tmp_path / "mlflow", run_name="tiny", params=cfg.tables()))
    run = train(cfg, callbacks=[seen.append, *map(as_callback, trackers)])
    for tracker in trackers:
        tracker.close()
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
        events = list((tmp_path / "tb").glob("*/events.out.tfevents.*"))  # the run's own folder
        assert events and events[0].stat().st_size > 0
    if has_mlflow:  # every row's scalars, at its env step, read back from the store
        from mlflow import MlflowClient

        client = MlflowClient(trackers[0].tracking_uri)
        history = client.get_metric_history(trackers[0].run_id, "eval_reward")
        assert [(m.step, m.value) for m in history] == [(int(r["env_steps"]), r["eval_reward"]) for r in seen]
        mlrun = client.get_run(trackers[0].run_id)
        assert mlrun.info.status == "FINISHED" and mlrun.data.params["ppo.num_envs"] == "4"
        assert set(mlrun.data.metrics) == set(scalars(seen[-1]))


def test_tensorboard_without_tensorboardx_is_a_clear_error(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_tbx(name, *args, **kwargs):
        if name.startswith("tensorboardX"):
            raise ImportError("no tensorboardX")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_tbx)
    from jaxtraffic.runs.tracking import TensorBoardWriter

    with pytest.raises(ValueError, match=r"jaxtraffic\[tb\]"):
        TensorBoardWriter(tmp_path / "tb")


def test_tensorboard_drops_the_steps_a_resume_logs_again(tmp_path):
    """An interrupted session logged up to 3 chunks, its checkpoint holds 1: the resumed session's rows replace
    chunks 2 and 3 (read back as TensorBoard reads them), none is drawn twice."""
    need("tensorboardX")
    accumulator = need("tensorboard.backend.event_processing.event_accumulator")
    from jaxtraffic.runs.tracking import TensorBoardWriter

    first = TensorBoardWriter(tmp_path)
    for k in (1, 2, 3):
        first.log(k * CHUNK, {"eval_reward": -float(k)})
    first.close()
    time.sleep(1.1)  # (event file names hold the second: the resumed session's file sorts after)
    resumed = TensorBoardWriter(tmp_path, purge_step=CHUNK + 1)  # what run_training passes: checkpoint + 1
    for k in (2, 3):
        resumed.log(k * CHUNK, {"eval_reward": 10.0 * k})
    resumed.close()
    acc = accumulator.EventAccumulator(str(tmp_path))
    acc.Reload()
    got = [(e.step, e.value) for e in acc.Scalars("train/eval_reward")]
    assert got == [(CHUNK, -1.0), (2 * CHUNK, 20.0), (3 * CHUNK, 30.0)]


def test_mlflow_tracker_logs_offline_to_a_directory(tmp_path):
    """The second tracker: an MLflow run in a directory's SQLite store, no server; the learning-curve row's
    non-numeric and non-finite fields are left out, as for TensorBoard."""
    mlflow = need("mlflow")
    from jaxtraffic.runs.tracking import MLflowTracker

    tracker = MLflowTracker(tmp_path / "store", experiment="tiny", params={"seed": 3})
    log = as_callback(tracker)
    log({"env_steps": CHUNK, "eval_reward": -2.0, "stopped": "no", "wall_s": float("nan")})
    log({"env_steps": 2 * CHUNK, "eval_reward": -1.0, "stopped": "no", "wall_s": 4.5})
    tracker.close()
    assert (tmp_path / "store" / "mlflow.db").exists()
    client = mlflow.MlflowClient(tracker.tracking_uri)
    assert [(m.step, m.value) for m in client.get_metric_history(tracker.run_id, "eval_reward")] == [
        (CHUNK, -2.0), (2 * CHUNK, -1.0)]
    assert [(m.step, m.value) for m in client.get_metric_history(tracker.run_id, "wall_s")] == [(2 * CHUNK, 4.5)]
    run = client.get_run(tracker.run_id)
    assert run.data.params == {"seed": "3"} and "stopped" not in run.data.metrics
    assert client.get_experiment(run.info.experiment_id).name == "tiny"
    again = MLflowTracker(tmp_path / "store", experiment="tiny")  # the same experiment, a second run
    assert client.get_run(again.run_id).info.experiment_id == run.info.experiment_id
    assert again.run_id != tracker.run_id
    again.close()
