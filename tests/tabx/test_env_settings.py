"""Environment variables the project reads, set wrong: each is named in one warning line and
the command goes on as documented (docs/reliability.md, "Bad input gets one line")."""

from __future__ import annotations

import jax

from tabx import native_lib
from tabx.scenarios import registry
from ued import compile_cache


def warning_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def test_scenario_dir_that_is_a_file_is_one_warning(tmp_path, monkeypatch, capsys):
    path = tmp_path / "a-file"
    path.write_text("x")
    monkeypatch.setenv(registry.USER_DIR_ENV, str(path))
    registry._warn_once.cache_clear()
    assert "crossfire" in registry.list_scenarios()  # the bundled ones still load
    registry.user_scenario_dir()
    lines = warning_lines(capsys.readouterr().err)
    assert lines == [f"warning: TABX_SCENARIO_DIR={path}: not a folder; no user scenario is "
                     "read from it (point it at a folder)"]


def test_native_setting_that_is_neither_on_nor_off_is_one_warning(monkeypatch, capsys):
    monkeypatch.setenv("TABX_NATIVE", "garbage")
    monkeypatch.setattr(native_lib, "_state", {})
    assert native_lib.native_enabled() and native_lib.native_enabled()
    assert warning_lines(capsys.readouterr().err) == [
        "warning: TABX_NATIVE='garbage': expected 1 or 0 (on or off); the native kernels "
        "stay on"]
    monkeypatch.setenv("TABX_NATIVE", "off")
    assert not native_lib.native_enabled() and capsys.readouterr().err == ""


def test_compile_cache_dir_that_cannot_be_written_is_one_warning(tmp_path, monkeypatch,
                                                                 capsys):
    """An existing folder that cannot be written (a read-only mount as root, else its
    permissions): the cache stays off with one line, rather than failing each write quietly.
    (A file in its place: tests/ued/test_compile_cache.py.)"""
    import os
    import subprocess

    import pytest

    folder = tmp_path / "cache"
    folder.mkdir()
    if os.geteuid() == 0:
        if subprocess.run(["mount", "--bind", "-o", "ro", str(folder), str(folder)],
                          capture_output=True).returncode:
            pytest.skip("no read-only bind mount here")
        undo = ["umount", "-l", str(folder)]
    else:
        folder.chmod(0o555)
        undo = ["chmod", "755", str(folder)]
    monkeypatch.setenv(compile_cache.ENV_VAR, str(folder))
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        assert compile_cache.enable() is None
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)
        subprocess.run(undo, check=False)
    lines = warning_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith(
        f"warning: compilation cache off: cannot write into {folder}"), lines
