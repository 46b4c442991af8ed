"""Provenance recorded with every result: commit, dirty flag, versions, machine."""

from __future__ import annotations

import re

import jax

from jaxtraffic.provenance import code_version, describe, provenance


def test_provenance_names_the_commit_and_the_versions():
    p = provenance()
    assert p["versions"]["jax"] == jax.__version__
    assert p["machine"]["backend"] == jax.default_backend() and p["machine"]["cores"] >= 1
    v = code_version()
    if v["commit"] is not None:  # a git checkout (CI clones the repository)
        assert re.fullmatch(r"[0-9a-f]{40}", v["commit"]) and isinstance(v["dirty"], bool)
        assert v["commit"][:12] in describe(p)
    assert f"jax {jax.__version__}" in describe(p)
