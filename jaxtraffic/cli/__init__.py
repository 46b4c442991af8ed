"""Command lines: ``cli.train`` (``python train.py``) and ``cli.evaluate`` (``python evaluate.py``)."""
