"""Test-session settings shared by every test module."""

import atexit
import os
import shutil
import tempfile

from tabx import xla_flags

# One persistent compilation cache (ued/compile_cache.py) for this test session, in a folder of
# its own that starts empty and is deleted at exit: never the user's cache. Ray actors, CLI
# subprocesses and in-process runs load a program that another process compiled instead of
# compiling it again (the Ray tests' actors each compiled the same learner and Explorer
# programs: about half of their time). A loaded program is the one XLA compiled, so results
# are the same bit for bit, and tabx.compile_counter counts a load as a compilation, so the
# no-recompile tests count the same. tests/test_compile_cache.py points the cache at folders
# of its own.
_COMPILE_CACHE = tempfile.mkdtemp(prefix="tabx-test-xla-")
atexit.register(shutil.rmtree, _COMPILE_CACHE, ignore_errors=True)
os.environ["TABX_COMPILE_CACHE_DIR"] = _COMPILE_CACHE

# Two CPU devices on every machine, whatever its core count (the `tabx` command makes one per
# core, see tabx/xla_flags.py), so the data-parallel learner path is tested the same way
# everywhere; then the command's other XLA settings, as its processes run. Set before JAX starts
# its backend; a flag the user set wins.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_force_host_platform_device_count=2").strip()
xla_flags.apply()

# Ray clusters in tests live on 127.0.0.1 (read when Ray is imported): without this Ray swaps
# 127.0.0.1 for the machine's outward address and a joining process cannot find the head.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

