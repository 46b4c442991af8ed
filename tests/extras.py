"""The optional extras' tests: skipped where an extra is not installed, but a failure where the
environment says every extra must be there (``JAXTRAFFIC_REQUIRE_EXTRAS=1``: ``.ci/run`` installs them
all, so that an ecosystem test cannot pass CI by being skipped)."""

from __future__ import annotations

import importlib
import importlib.util
import os
from types import ModuleType

import pytest

REQUIRED = os.environ.get("JAXTRAFFIC_REQUIRE_EXTRAS", "") not in ("", "0")


def need(module: str) -> ModuleType:
    """``module`` imported; skip the test (module) when it is missing, unless extras are required."""
    if REQUIRED:
        try:
            return importlib.import_module(module)
        except ImportError as err:
            pytest.fail(f"JAXTRAFFIC_REQUIRE_EXTRAS=1 and {module} does not import: {err}", pytrace=False)
    return pytest.importorskip(module)


def available(module: str) -> bool:
    """Whether ``module`` is installed (for a test with an optional part); True or a failure when extras
    are required."""
    if REQUIRED:
        need(module)
        return True
    return importlib.util.find_spec(module) is not None
