"""The package as a user installs it: `tabx --version`, `python -m tabx`, type hints marked for
type checkers (py.typed), the shipped training configs found by name from any directory, and
(slow) the built wheel installed into a fresh virtual environment and run from there."""

from __future__ import annotations

import os
import subprocess
import sys
import venv
from pathlib import Path

import jax
import pytest

import tabx
from tabx_ued.cli import main
from ued import config_files
from ued.config import ConfigError, load_config
from ued.config_files import list_configs, resolve_config

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("tabx", "level_buffer", "ued", "workers", "tabx_bench", "tabx_ued")


def test_version_flag_names_the_package_and_jax(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"tabx-ued {tabx.__version__} ") and f"jax {jax.__version__}" in out


def test_python_dash_m_tabx_runs_the_command(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "tabx", "train", "--list-configs"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == list_configs()


def test_every_package_is_marked_typed():
    for package in PACKAGES:
        assert (ROOT / package / "py.typed").is_file(), package


def test_shipped_configs_resolve_by_name_folder_or_stem(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # names do not depend on the working directory
    names = list_configs()
    assert "ued/quickstart" in names and "marl/mappo_crossfire" in names
    sweeps = list((ROOT / "configs" / "sweeps").glob("*.yaml"))
    assert sweeps and not any(name.startswith("sweeps/") for name in names)
    assert len(names) == len(list((ROOT / "configs").rglob("*.yaml"))) - len(sweeps)
    quickstart = (ROOT / "configs" / "ued" / "quickstart.yaml").resolve()
    for text in ("quickstart", "ued/quickstart", "ued/quickstart.yaml", "quickstart.yaml"):
        assert resolve_config(text).resolve() == quickstart
    assert load_config("ued/accel_zone").ued.method == "accel"
    # A file of the same name in the working directory is a path, and a path wins.
    (tmp_path / "quickstart.yaml").write_text("algorithm: ippo\n")
    assert resolve_config("quickstart.yaml") == Path("quickstart.yaml")
    assert resolve_config("quickstart").resolve() == quickstart


def test_a_name_that_is_neither_file_nor_config_lists_close_names(capsys, monkeypatch):
    with pytest.raises(ConfigError, match=r"quikstart: cannot read the config .*close names: "
                                          r"ued/quickstart"):
        load_config("quikstart")
    code = main(["train", "ued/acel_zone"])
    err = capsys.readouterr().err
    assert code == 2 and "close names: ued/accel_zone" in err and "Traceback" not in err
    # A stem that two folders share must be named with its folder.
    two = {"marl/same": Path("a.yaml"), "ued/same": Path("b.yaml")}
    monkeypatch.setattr(config_files, "bundled_configs", lambda: two)
    with pytest.raises(ConfigError, match="ambiguous: use one of marl/same, ued/same"):
        config_files.resolve_config("same")


@pytest.mark.slow
def test_the_wheel_installs_and_runs_from_a_fresh_environment(tmp_path):
    """Build the wheel, install it (no dependencies: they come from this environment's
    site-packages) into a new virtual environment, and run `tabx` from a directory far from the
    repository, with nothing of the repository on the path."""
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                            str(wheels), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr
    (wheel,) = wheels.glob("tabx_ued-*.whl")
    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)
    python = env_dir / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    install = subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps",
                              "--no-index", str(wheel)], capture_output=True, text=True,
                             env=env, timeout=600)
    assert install.returncode == 0, install.stderr
    work = tmp_path / "elsewhere"
    work.mkdir()

    def tabx_cmd(*argv: str) -> str:
        done = subprocess.run([str(env_dir / "bin" / "tabx"), *argv], cwd=work, env=env,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        return done.stdout

    where = subprocess.run([str(python), "-c", "import ued, tabx; print(ued.__file__); "
                            "print(tabx.__file__)"], cwd=work, env=env, capture_output=True,
                           text=True, timeout=120)
    assert all(line.startswith(str(env_dir)) for line in where.stdout.split()), where.stdout
    native = subprocess.run([str(python), "-c", "from tabx.native_lib import native_available; "
                             "print(native_available())"], cwd=work, env=env,
                            capture_output=True, text=True, timeout=300)
    assert native.stdout.strip() == "True", native.stderr  # the kernel source ships in the wheel
    assert tabx_cmd("--version").startswith(f"tabx-ued {tabx.__version__}")
    assert "crossfire" in tabx_cmd("scenarios", "list")
    assert "ued/quickstart" in tabx_cmd("train", "--list-configs").split()
    out = tabx_cmd("train", "quickstart", "learner.num_envs=4", "learner.num_steps=16",
                   "env.max_steps=16",
                   "ued.eval_suites=[]", "ued.buffer_size=8", "--max-updates", "1",
                   "--run-dir", str(work / "run"), "--quiet")
    assert out.strip().endswith(str(work / "run"))
    assert any((work / "run" / "checkpoints").iterdir())
