"""Issue 50, round four of the ecosystem: ``gymnax.make("jaxtraffic/Gain-v0")`` in either import order (an
import hook registers the id when gymnax is imported after jaxtraffic), checked in fresh interpreters with a
stand-in gymnax package (always) and with the real one (when the ``[gymnax]`` extra is installed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from extras import available

REPO = Path(__file__).resolve().parents[1]

# a stand-in for gymnax >= 1.0's registry (register / registered_envs / make), as small as the real API
FAKE_GYMNAX = '''
_registry = {}
registered_envs = []
def register(env_id, factory):
    if env_id in _registry:
        raise ValueError(f"{env_id} is already registered")
    _registry[env_id] = factory
    registered_envs.append(env_id)
def make(env_id, **kwargs):
    return _registry[env_id], kwargs
'''

ORDERS = {"gymnax first": "import gymnax, jaxtraffic", "jaxtraffic first": "import jaxtraffic, gymnax",
          "a gymnax submodule first": "import jaxtraffic; import gymnax.sub; import gymnax",
          "after a find_spec probe": "import importlib.util, jaxtraffic; importlib.util.find_spec('gymnax'); "
                                     "import gymnax"}


def _python(code: str, *path: Path) -> str:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": os.pathsep.join(map(str, (*path, REPO)))}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.fixture
def fake_gymnax(tmp_path) -> Path:
    (tmp_path / "gymnax").mkdir()
    (tmp_path / "gymnax" / "__init__.py").write_text(FAKE_GYMNAX)
    (tmp_path / "gymnax" / "sub.py").write_text("X = 1\n")
    return tmp_path


@pytest.mark.parametrize("order", ORDERS)
def test_gymnax_make_finds_the_id_in_either_import_order(order, fake_gymnax):
    code = (f"{ORDERS[order]}; import sys; factory, kw = gymnax.make('jaxtraffic/Gain-v0'); "
            "print(gymnax.registered_envs, factory.__name__, "
            "[type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    # registered once, by jaxtraffic's factory, and the one-shot hook gone from sys.meta_path
    assert _python(code, fake_gymnax) == "['jaxtraffic/Gain-v0'] _make_gymnax_env 0"


def test_import_jaxtraffic_alone_imports_no_gymnax_and_leaves_one_hook(fake_gymnax):
    code = ("import sys, jaxtraffic; from jaxtraffic._registration import register_gymnax; register_gymnax(); "
            "print('gymnax' in sys.modules, [type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    assert _python(code, fake_gymnax) == "False 1"  # (register_gymnax again: still one hook)


def test_no_hook_without_gymnax_installed(tmp_path):
    code = ("import importlib.util, sys, jaxtraffic; "
            "print(importlib.util.find_spec('gymnax') is None, "
            "[type(f).__name__ for f in sys.meta_path].count('_GymnaxHook'))")
    found = _python(code, tmp_path)
    assert found in ("True 0", "False 1")  # no gymnax: no hook; gymnax installed: a hook until it is imported


@pytest.mark.skipif(not available("gymnax"), reason="the [gymnax] extra is not installed")
@pytest.mark.parametrize("order", ["import gymnax, jaxtraffic", "import jaxtraffic, gymnax"])
def test_real_gymnax_makes_the_env_in_either_import_order(order):
    made = _python(f"{order}; env, p = gymnax.make('jaxtraffic/Gain-v0', n_points=21); "
                   "print(type(env).__name__, int(p.horizon))")
    assert made == "GainGymnaxEnv 1000"  # the default 100 s horizon, dt 0.1 s


# ----------------------------------------------------------------------------- the committed notebook
NOTEBOOK = REPO / "examples" / "quickstart.ipynb"


def _outputs() -> list[list[dict]]:
    import json

    nb = json.loads(NOTEBOOK.read_text())
    return [c["outputs"] for c in nb["cells"] if c["cell_type"] == "code"]


def test_the_committed_notebook_shows_its_outputs_small_and_plain():
    outputs = _outputs()
    assert all(outputs[1:]), "a code cell without output: execute the notebook before committing it"
    assert not [o for o in outputs[0] if o["output_type"] == "execute_result"]  # no stray value (the device count)
    texts = ["".join(o.get("text", "")) + str(o.get("data", {}).get("text/plain", "")) for c in outputs for o in c]
    assert not any("np.float" in t or "Traceback" in t for t in texts)
    batch = "".join(texts)
    assert "plant delay D = 4 s: final density L2" in batch and "veh/km" in batch
    images = [o["data"]["image/png"] for c in outputs for o in c if "image/png" in o.get("data", {})]
    assert 2 <= len(images) <= 3 and sum(map(len, images)) < 400_000  # (base64 characters)
    assert NOTEBOOK.stat().st_size < 500_000


def test_the_gymnasium_cell_says_when_gym_is_missing(monkeypatch, capsys):
    """Without gymnasium the cell prints how to install it (and shows nothing else)."""
    import builtins
    import json

    nb = json.loads(NOTEBOOK.read_text())
    cell = next("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"
                and "gymnasium.make" in "".join(c["source"]))
    real_import = builtins.__import__

    def no_gym(name, *args, **kwargs):
        if name.startswith("gymnasium"):
            raise ImportError("no gymnasium")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_gym)
    namespace: dict = {"N_POINTS": 41}
    exec(compile(cell, "quickstart.ipynb gymnasium cell", "exec"), namespace)  # noqa: S102
    assert namespace["frame_fig"] is None
    assert 'Gymnasium is not installed' in capsys.readouterr().out and '[gym]' in cell
