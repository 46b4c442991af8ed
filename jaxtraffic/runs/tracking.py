"""Experiment tracking: the trainers' logged scalars behind one small protocol (``Tracker``).

Both trainers hand every learning-curve row (a dict, one per chunk) to their callbacks; ``as_callback(tracker)``
turns a ``Tracker`` into such a callback: it receives the row's numeric, finite fields (``scalars``) against the
row's ``env_steps``. Two trackers, each an optional extra, work offline:

* ``TensorBoardWriter(logdir)``: scalars ``train/<field>`` (tensorboardX, ``pip install 'jaxtraffic[tb]'``,
  which brings the viewer too: ``tensorboard --logdir DIR``); ``jaxtraffic-train --tensorboard DIR`` opens one.
  A resumed run continues from its checkpoint, which may be older than the last rows the interrupted session
  logged: ``purge_step`` (the first step the new session logs; ``run_training`` passes the checkpoint's
  env_steps + 1) makes TensorBoard drop the old session's events from that step on, so no step is drawn twice.
* ``MLflowTracker(store)``: an MLflow run (``pip install 'jaxtraffic[mlflow]'``: mlflow-skinny and the SQLite
  store's sqlalchemy/alembic; no server). ``store``: a directory (its ``mlflow.db``, created) or any MLflow
  tracking URI. From Python: ``train(config, callbacks=[as_callback(tracker)])``, then ``tracker.close()``.

A tracker of your own needs only ``log(step, scalars)`` and ``close()``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

__all__ = ["MLflowTracker", "TensorBoardWriter", "Tracker", "as_callback", "scalars"]


class Tracker(Protocol):
    """Where a training's scalars go: ``log`` once per learning-curve row, ``close`` at the end."""

    def log(self, step: int, values: Mapping[str, float]) -> None:
        """Record ``values`` (name -> finite number) at ``step`` (environment steps, all environments)."""
        ...

    def close(self) -> None:
        """Flush and release (the training is over)."""
        ...


def scalars(row: Mapping[str, Any]) -> dict[str, float]:
    """The numeric, finite fields of a learning-curve row except its step (``env_steps``), as floats."""
    return {k: float(v) for k, v in row.items()
            if k != "env_steps" and isinstance(v, (int, float)) and math.isfinite(v)}


def as_callback(tracker: Tracker) -> Callable[[dict], None]:
    """The training callback that logs each learning-curve row's ``scalars`` at its ``env_steps``."""
    return lambda row: tracker.log(int(row["env_steps"]), scalars(row))


class TensorBoardWriter:
    """A ``Tracker`` writing TensorBoard scalars ``train/<name>`` (tensorboardX)."""

    def __init__(self, logdir: str | Path, purge_step: int | None = None):
        try:
            from tensorboardX import SummaryWriter
        except ImportError as err:
            raise ValueError("--tensorboard needs tensorboardX: pip install 'jaxtraffic[tb]'") from err
        self.logdir = Path(logdir)
        self._writer = SummaryWriter(str(self.logdir), purge_step=purge_step)

    def log(self, step: int, values: Mapping[str, float]) -> None:
        for name, value in values.items():
            self._writer.add_scalar(f"train/{name}", value, step)
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


def _mlflow_uri(store: str | Path) -> str:
    """A tracking URI as given, or a directory's SQLite store (the directory created)."""
    if "://" in str(store):
        return str(store)
    path = Path(store).absolute()
    path.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{path / 'mlflow.db'}"


class MLflowTracker:
    """A ``Tracker`` logging to one MLflow run (the client API: no global MLflow state is touched).

    ``store``: a directory (an SQLite store ``mlflow.db`` there, offline) or an MLflow tracking URI;
    ``experiment``: its name (created if new); ``run_name``; ``params``: logged once (e.g. ``config.tables()``: a
    nested mapping is logged with dotted keys, ``ppo.num_envs``).
    ``run_id`` names the run (``mlflow.MlflowClient(tracking_uri).get_metric_history(run_id, name)``)."""

    def __init__(self, store: str | Path, experiment: str = "jaxtraffic", run_name: str | None = None,
                 params: Mapping[str, Any] | None = None):
        try:
            from mlflow import MlflowClient
            from mlflow.entities import Metric, Param
        except ImportError as err:
            raise ValueError("MLflowTracker needs mlflow: pip install 'jaxtraffic[mlflow]'") from err
        self.tracking_uri = _mlflow_uri(store)
        self._client, self._metric = MlflowClient(self.tracking_uri), Metric
        found = self._client.get_experiment_by_name(experiment)
        experiment_id = found.experiment_id if found else self._client.create_experiment(experiment)
        self.run_id = self._client.create_run(experiment_id, run_name=run_name).info.run_id
        if params:  # (MLflow keeps parameter values as strings of at most 6000 characters)
            flat = {f"{k}.{k2}": v2 for k, v in params.items() if isinstance(v, Mapping) for k2, v2 in v.items()}
            flat.update({k: v for k, v in params.items() if not isinstance(v, Mapping)})
            self._client.log_batch(self.run_id, params=[Param(k, str(v)[:6000]) for k, v in flat.items()])

    def log(self, step: int, values: Mapping[str, float]) -> None:
        now = int(time.time() * 1000)
        self._client.log_batch(self.run_id, metrics=[self._metric(k, v, now, step) for k, v in values.items()])

    def close(self) -> None:
        self._client.set_terminated(self.run_id)
