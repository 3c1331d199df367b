"""`tabx.xla_flags`: the XLA:CPU settings of the `tabx` command, when `apply()` leaves XLA_FLAGS
alone, and who applies them (not `import tabx`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tabx import xla_flags


@pytest.fixture
def flags(monkeypatch):
    """Run `apply()` on a given XLA_FLAGS and core count; return the resulting XLA_FLAGS."""
    monkeypatch.delenv("TABX_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.setattr(xla_flags, "jaxlib_is_measured", lambda: True)

    def run(initial: str, cores: int = 4) -> str:
        monkeypatch.setenv("XLA_FLAGS", initial)
        monkeypatch.setattr(xla_flags, "usable_cores", lambda: cores)
        xla_flags.apply()
        return os.environ["XLA_FLAGS"]

    return run


def test_one_cpu_device_per_core_and_no_ynn_fusion(flags):
    assert flags("", cores=4).split() == ["--xla_cpu_experimental_ynn_fusion_type=",
                                          "--xla_force_host_platform_device_count=4"]


def test_the_users_own_flags_win(flags):
    result = flags("--xla_force_host_platform_device_count=3 --xla_cpu_foo=1", cores=4)
    assert "--xla_force_host_platform_device_count=3" in result
    assert "device_count=4" not in result and "--xla_cpu_foo=1" in result
    assert flags("--xla_cpu_experimental_ynn_fusion_type=dot", cores=1) == (
        "--xla_cpu_experimental_ynn_fusion_type=dot")


def test_one_core_gets_one_device(flags):
    assert "device_count" not in flags("", cores=1)


def test_a_pinned_group_member_gets_a_device_per_core_it_keeps(flags, monkeypatch):
    """`apply` sized the devices to the machine; pinned to 1 of 4 cores the member gets 1
    device, to 2 of them 2; its other flags stay."""
    flags("--xla_cpu_foo=1", cores=4)
    monkeypatch.setattr(xla_flags, "usable_cores", lambda: 1)
    assert xla_flags.match_devices_to_cores()
    assert "device_count" not in os.environ["XLA_FLAGS"] and "--xla_cpu_foo=1" in os.environ[
        "XLA_FLAGS"]
    monkeypatch.setattr(xla_flags, "usable_cores", lambda: 2)
    assert xla_flags.match_devices_to_cores()
    assert "--xla_force_host_platform_device_count=2" in os.environ["XLA_FLAGS"].split()
    assert not xla_flags.match_devices_to_cores()  # nothing left to change


def test_opt_out_and_unmeasured_jaxlib_leave_xla_flags_alone(flags, monkeypatch):
    monkeypatch.setenv("TABX_KEEP_XLA_FLAGS", "1")
    assert flags("--xla_cpu_foo=1") == "--xla_cpu_foo=1"
    monkeypatch.delenv("TABX_KEEP_XLA_FLAGS")
    monkeypatch.setattr(xla_flags, "jaxlib_is_measured", lambda: False)
    assert flags("") == ""


def test_usable_cores_is_positive():
    assert xla_flags.usable_cores() >= 1


def test_import_tabx_changes_no_environment_variable_and_a_ray_actor_module_applies_them():
    """In a fresh process: importing the simulator leaves the environment as it was and starts
    no JAX backend (XLA_FLAGS can still be set after it); the module Ray loads in an actor's
    process applies the command's settings, and the command table starts no backend either."""
    code = ("import os\n"
            "import jax\n"  # JAX sets variables of its own when imported (TF_CPP_MIN_LOG_LEVEL)
            "before = dict(os.environ)\n"
            "import tabx, tabx.env, tabx.rollout, tabx.scenarios, tabx.render, tabx.marl\n"
            "assert dict(os.environ) == before, 'import tabx changed the environment'\n"
            "from jax._src import xla_bridge\n"
            "import workers.ray.actors, tabx_ued.commands\n"
            "assert not xla_bridge.backends_are_initialized(), 'an import started JAX'\n"
            "print(os.environ.get('XLA_FLAGS', ''))\n")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "TABX_KEEP_XLA_FLAGS")}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[2]),
                                         env.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    if xla_flags.jaxlib_is_measured():
        assert "--xla_cpu_experimental_ynn_fusion_type=" in done.stdout.split()
