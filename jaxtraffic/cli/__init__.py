"""Command lines: ``cli.train`` (``python train.py``) and ``cli.evaluate`` (``python evaluate.py``).

Importing this package splits a CPU host into one XLA device per core (``split_host_devices``; opt
out with ``JAXTRAFFIC_NO_DEVICE_SPLIT=1``), before jax starts: the command lines' default, which a
plain ``import jaxtraffic`` does not impose on a library user's process. ``DEVICE_SPLIT``: the
device count set, or None when nothing was changed.
"""

from jaxtraffic.platform.devices import split_host_devices

DEVICE_SPLIT = split_host_devices()
