"""What every training run shares, whatever its algorithm: the checkpoint format and run-directory files
(``checkpoint``), the run directory's ownership and signals (``session``), the learning curve (``curve``),
TensorBoard (``tensorboard``) and the host training loop (``loop``)."""
