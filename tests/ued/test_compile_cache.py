"""ued/compile_cache.py: where the persistent compilation cache lives, when it stays off, and
that a second process loads a program the first one compiled (separate processes: JAX's cache
settings are global and fixed once a process first uses them)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ued import compile_cache
from ued.config import ConfigError, RunSection

PROGRAM = """
import json, sys
import jax, jax.numpy as jnp
from ued import compile_cache
compile_cache.MIN_COMPILE_SECONDS = 0.0  # cache even this small program
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
path = compile_cache.enable()
f = jax.jit(lambda x: jnp.tanh(x) @ x.T + 1.0)
f(jnp.ones((8, 8))).block_until_ready()
print(json.dumps({"path": str(path) if path else None,
                  "hits": events.count("/jax/compilation_cache/cache_hits")}))
"""


def run_program(env_dir: str) -> dict:
    env = {**__import__("os").environ, compile_cache.ENV_VAR: env_dir}
    out = subprocess.run([sys.executable, "-c", PROGRAM], env=env, capture_output=True,
                         text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_process_loads_what_the_first_compiled(tmp_path):
    folder = tmp_path / "xla"
    first = run_program(str(folder))
    assert first == {"path": str(folder), "hits": 0}
    assert any(folder.iterdir()), "nothing was written to the cache"
    second = run_program(str(folder))
    assert second["hits"] >= 1


def test_off_leaves_the_cache_off(tmp_path):
    assert run_program("off") == {"path": None, "hits": 0}


def test_cache_dir_default_and_override(monkeypatch, tmp_path):
    monkeypatch.delenv(compile_cache.ENV_VAR, raising=False)
    assert compile_cache.cache_dir() == Path(compile_cache.DEFAULT_DIR).expanduser()
    monkeypatch.setenv(compile_cache.ENV_VAR, str(tmp_path))
    assert compile_cache.cache_dir() == tmp_path
    monkeypatch.setenv(compile_cache.ENV_VAR, "OFF")
    assert compile_cache.cache_dir() is None
    assert compile_cache.enable(False) is None


def test_unwritable_folder_warns_and_stays_off(monkeypatch, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(compile_cache.ENV_VAR, str(blocker / "xla"))
    # As in a process where nothing has set a cache yet (the test session shares one).
    previous = compile_cache.jax.config.jax_compilation_cache_dir
    compile_cache.jax.config.update("jax_compilation_cache_dir", None)
    try:
        assert compile_cache.enable() is None
    finally:
        compile_cache.jax.config.update("jax_compilation_cache_dir", previous)
    assert "compilation cache off" in capsys.readouterr().err


def test_run_section_compile_cache_must_be_a_bool():
    from ued.config import config_from_dict

    with pytest.raises(ConfigError, match="compile_cache"):
        config_from_dict({"run": {"compile_cache": "sometimes"}}, source="test.yaml")
    assert RunSection().compile_cache is True
