"""Test-session settings shared by every test module."""

import os

# Tests never read or write the user's persistent compilation cache (ued/compile_cache.py): a
# warm cache would skip compilations that some tests count. Subprocesses inherit the setting;
# tests/test_compile_cache.py points it at a temporary folder where it needs one.
os.environ["TABX_COMPILE_CACHE_DIR"] = "off"

# Two CPU devices on every machine, whatever its core count (tabx makes one per core, see
# tabx/_xla_flags.py), so the data-parallel learner path is tested the same way everywhere.
# Set before JAX starts its backend; a flag the user set wins.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_force_host_platform_device_count=2").strip()

# Ray clusters in tests live on 127.0.0.1 (read when Ray is imported): without this Ray swaps
# 127.0.0.1 for the machine's outward address and a joining process cannot find the head.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
