"""Gradient-based and derivative-free training of gain laws, one package: the settings (``config``), the
rollout objective and Adam (``objective``), the cross-entropy method (``cem``), their hooks for the shared
training loop and the saved policy are ``runs.gradient``. Importing the package imports nothing else."""
