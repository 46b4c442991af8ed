"""The lab: what every training run shares, whatever its algorithm. The run's configuration (``config``),
the checkpoint format and run-directory files (``checkpoint``), the run directory's ownership and signals
(``session``), the learning curve (``curve``), experiment tracking (``tracking``: TensorBoard, MLflow), the host
training loop
(``loop``), each algorithm's trainer and saved policy (``ppo/``, ``gradient/``) and ``load_policy``
(``policy``): a trained run's controller, whatever the algorithm, and ``train_run`` (``train``): train the run
a config describes, whatever the algorithm. Configs are read and written as TOML (``config.toml``:
``read_config``, ``write_config``)."""

from jaxtraffic.runs.config.toml import read_config, write_config
from jaxtraffic.runs.policy import load_policy
from jaxtraffic.runs.train import train_run

__all__ = ["load_policy", "read_config", "train_run", "write_config"]
