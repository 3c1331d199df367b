"""Test-session settings shared by every test module."""

import os

# Tests never read or write the user's persistent compilation cache (ued/compile_cache.py): a
# warm cache would skip compilations that some tests count. Subprocesses inherit the setting;
# tests/test_compile_cache.py points it at a temporary folder where it needs one.
os.environ["TABX_COMPILE_CACHE_DIR"] = "off"
