"""Provenance recorded with every result: commit, dirty flag, versions, machine."""

from __future__ import annotations

import re

import jax

from jaxtraffic.io.provenance import code_version, describe, provenance


def test_provenance_names_the_commit_and_the_versions():
    p = provenance()
    assert p["versions"]["jax"] == jax.__version__
    assert p["machine"]["backend"] == jax.default_backend() and p["machine"]["cores"] >= 1
    v = code_version()
    if v["commit"] is not None:  # a git checkout (CI clones the repository)
        assert re.fullmatch(r"[0-9a-f]{40}", v["commit"]) and isinstance(v["dirty"], bool)
        assert v["commit"][:12] in describe(p)
    assert f"jax {jax.__version__}" in describe(p)


def test_installed_inside_another_git_repository_records_the_version_not_that_commit(tmp_path):
    """A wheel installed into a virtual environment inside a user's own git repository: the package's
    parent directory lies in *their* checkout, whose commit says nothing of jaxtraffic's code."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import jaxtraffic

    user = tmp_path / "their-project"
    site = user / ".venv" / "lib" / "site-packages"
    (site / "jaxtraffic" / "io").mkdir(parents=True)
    for name in ("_version.py", "io/provenance.py"):
        shutil.copy(Path(jaxtraffic.__file__).parent / name, site / "jaxtraffic" / name)
    for package in ("", "io/"):
        (site / "jaxtraffic" / package / "__init__.py").write_text("")
    git = ["git", "-C", str(user), "-c", "user.name=u", "-c", "user.email=u@example.com"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "commit", "-q", "--allow-empty", "-m", "theirs"], check=True)
    code = "import json; from jaxtraffic.io.provenance import code_version; print(json.dumps(code_version()))"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                         env={"PATH": __import__("os").environ["PATH"], "PYTHONPATH": str(site)})
    assert out.returncode == 0, out.stderr
    import json

    v = json.loads(out.stdout)
    assert v == {"version": jaxtraffic.__version__, "commit": None, "dirty": None}
    assert code_version()["version"] == jaxtraffic.__version__
