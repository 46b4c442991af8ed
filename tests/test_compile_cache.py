"""The command-line jobs' persistent compilation cache (jaxtraffic.platform.compile_cache).

The rules that leave the cache off are checked in-process (they change nothing); enabling it changes
jax's process-wide configuration, so that is checked in subprocesses: the first stores the program,
the second loads it (a cache hit) and computes the same bits.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax

from jaxtraffic.platform import compile_cache

REPO = Path(__file__).resolve().parents[1]


def test_default_dir_follows_xdg(tmp_path):
    assert compile_cache.default_dir({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "jaxtraffic" / "xla"
    assert compile_cache.default_dir({}) == Path.home() / ".cache" / "jaxtraffic" / "xla"


def test_left_off_or_to_the_user(tmp_path):
    # an earlier in-process train.py / evaluate.py of the suite may have set the config: start from none
    saved = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        for value in ("0", "off", "False", "no"):
            assert compile_cache.enable(env={compile_cache.ENV: value}) is None
        # the user's own jax cache directory wins over ours, even with a path of ours given
        user = {"JAX_COMPILATION_CACHE_DIR": str(tmp_path / "mine"), compile_cache.ENV: str(tmp_path / "ours")}
        assert compile_cache.enable(env=user) is None
        assert jax.config.jax_compilation_cache_dir is None  # the rules above do not touch the config
        assert not (tmp_path / "ours").exists()
    finally:
        jax.config.update("jax_compilation_cache_dir", saved)


_CHILD = textwrap.dedent("""
    import sys, jax, jax.numpy as jnp
    from jaxtraffic.platform import compile_cache
    hits = []
    jax.monitoring.register_event_listener(
        lambda name, **kw: hits.append(1) if name == "/jax/compilation_cache/cache_hits" else None)
    where = compile_cache.enable()
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # store even a tiny program
    f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) * 1.000123) / 3.0)
    y = f(jnp.linspace(0.0, 7.0, 1001, dtype=jnp.float32))
    print(where, len(hits), y.view(jnp.int32).sum().item())
""")


def _child(env: dict) -> list[str]:
    out = subprocess.run([sys.executable, "-c", _CHILD], env=env, cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_second_process_loads_the_first_ones_program(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env[compile_cache.ENV] = str(tmp_path / "cache")
    where, hits, bits = _child(env)
    assert where == str(tmp_path / "cache") and hits == "0"
    assert oct((tmp_path / "cache").stat().st_mode & 0o777) == oct(0o700)  # private: jax runs what it loads
    assert any(p.name.endswith("-cache") for p in (tmp_path / "cache").iterdir())
    where2, hits2, bits2 = _child(env)
    assert (where2, int(hits2) >= 1, bits2) == (where, True, bits)
    # off: no directory, no hit
    env_off = {**env, compile_cache.ENV: "0", "XDG_CACHE_HOME": str(tmp_path / "xdg")}
    assert _child(env_off)[:2] == ["None", "0"]
    assert not (tmp_path / "xdg").exists()
