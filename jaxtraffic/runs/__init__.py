"""The lab: what every training run shares, whatever its algorithm. The run's configuration (``config``),
the checkpoint format and run-directory files (``checkpoint``), the run directory's ownership and signals
(``session``), the learning curve (``curve``), TensorBoard (``tensorboard``), the host training loop
(``loop``), each algorithm's trainer and saved policy (``ppo/``, ``gradient/``) and ``load_policy``
(``policy``): a trained run's controller, whatever the algorithm; ``train_run(config)`` trains one."""

from jaxtraffic.runs.policy import load_policy
from jaxtraffic.runs.train import train_run

__all__ = ["load_policy", "train_run"]
