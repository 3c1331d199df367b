"""`tabx._xla_flags`: the XLA:CPU settings `import tabx` adds to XLA_FLAGS, and when it leaves
them alone."""

from __future__ import annotations

import os

import pytest

from tabx import _xla_flags


@pytest.fixture
def flags(monkeypatch):
    """Run `apply()` on a given XLA_FLAGS and core count; return the resulting XLA_FLAGS."""
    monkeypatch.delenv("TABX_KEEP_XLA_FLAGS", raising=False)
    monkeypatch.setattr(_xla_flags, "jaxlib_is_measured", lambda: True)

    def run(initial: str, cores: int = 4) -> str:
        monkeypatch.setenv("XLA_FLAGS", initial)
        monkeypatch.setattr(_xla_flags, "usable_cores", lambda: cores)
        _xla_flags.apply()
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


def test_opt_out_and_unmeasured_jaxlib_leave_xla_flags_alone(flags, monkeypatch):
    monkeypatch.setenv("TABX_KEEP_XLA_FLAGS", "1")
    assert flags("--xla_cpu_foo=1") == "--xla_cpu_foo=1"
    monkeypatch.delenv("TABX_KEEP_XLA_FLAGS")
    monkeypatch.setattr(_xla_flags, "jaxlib_is_measured", lambda: False)
    assert flags("") == ""


def test_usable_cores_is_positive():
    assert _xla_flags.usable_cores() >= 1
