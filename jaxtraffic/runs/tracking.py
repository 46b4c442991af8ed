"""Experiment tracking: the trainers' logged scalars behind one small protocol (``Tracker``).

Both trainers hand every learning-curve row (a dict, one per chunk) to their callbacks; ``as_callback(tracker)``
turns a ``Tracker`` into such a callback: it receives the row's numeric, finite fields (``scalars``) against the
row's ``env_steps``. Two trackers, each an optional extra, work offline:

* ``TensorBoardWriter(logdir)``: scalars ``train/<field>`` (tensorboardX, ``pip install 'jaxtraffic[tb]'``,
  which brings the viewer too: ``tensorboard --logdir DIR``); ``jaxtraffic-train --tensorboard DIR`` opens one
  in the run's own folder ``DIR/<run directory's name>_<UTC start time>`` (``board_dir``: TensorBoard lists each
  folder as a run; a resumed run continues its folder), with the run's config.toml as the text ``config``.
  A resumed run continues from its checkpoint, which may be older than the last rows the interrupted session
  logged: ``purge_step`` (the first step the new session logs; ``run_training`` passes the checkpoint's
  env_steps + 1) makes TensorBoard drop the old session's events from that step on, so no step is drawn twice.
* ``MLflowTracker(store)``: an MLflow run (``pip install 'jaxtraffic[mlflow]'``: mlflow-skinny and the SQLite
  store's sqlalchemy/alembic; no server). ``store``: a directory (its ``mlflow.db``, created) or any MLflow
  tracking URI. ``jaxtraffic-train --mlflow STORE`` opens one (named like the TensorBoard folder, the config's
  fields as its parameters); from Python: ``train(config, callbacks=[as_callback(tracker)])``, then
  ``tracker.close()``.

A tracker of your own needs only ``log(step, scalars)`` and ``close()``.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

from jaxtraffic.io.files import atomic_write_text

__all__ = ["MLflowTracker", "TensorBoardWriter", "Tracker", "as_callback", "board_dir", "run_name", "scalars"]

RUN_MARK = "jaxtraffic_run.txt"  # in each of board_dir's folders: the run directory it logs (absolute path)


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


def run_name(run_dir: str | Path) -> str:
    """A run's name in the trackers: its directory's name and the UTC time now, ``default_20261205-163000``."""
    return f"{Path(run_dir).resolve().name}_{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"


def board_dir(logdir: str | Path, run_dir: str | Path, resume: bool) -> Path:
    """The run's own TensorBoard folder under ``logdir`` (created): ``logdir/<run_name>`` (``-1``, ``-2``, ... if
    taken), marked with the run directory it logs (``RUN_MARK``); on ``resume``, the newest folder marked with
    ``run_dir``, if any, so that a resumed run continues its curves."""
    logdir, run = Path(logdir), str(Path(run_dir).resolve())
    if resume and logdir.is_dir():
        mine = sorted(p for p in logdir.iterdir() if (p / RUN_MARK).is_file()
                      and (p / RUN_MARK).read_text(errors="replace").strip() == run)
        if mine:
            return mine[-1]
    name = run_name(run)
    for k in itertools.count():
        path = logdir / (name if k == 0 else f"{name}-{k}")
        try:
            path.mkdir(parents=True)
            break
        except FileExistsError:
            continue
    atomic_write_text(path / RUN_MARK, run + "\n")
    return path


class TensorBoardWriter:
    """A ``Tracker`` writing TensorBoard scalars ``train/<name>`` (tensorboardX) into ``logdir`` itself (see
    ``board_dir`` for a run's own folder); ``config_text`` (e.g. the run's config.toml) is logged once as the
    text ``config`` at ``purge_step`` (0 if None)."""

    def __init__(self, logdir: str | Path, purge_step: int | None = None, config_text: str | None = None):
        try:
            from tensorboardX import SummaryWriter
        except ImportError as err:
            raise ValueError("--tensorboard needs tensorboardX: pip install 'jaxtraffic[tb]'") from err
        self.logdir = Path(logdir)
        self._writer = SummaryWriter(str(self.logdir), purge_step=purge_step)
        if config_text is not None:  # (markdown: a code block keeps the TOML's layout)
            self._writer.add_text("config", f"```toml\n{config_text}\n```", purge_step or 0)
            self._writer.flush()

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
