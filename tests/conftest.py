"""Test-session settings shared by every test module."""

import atexit
import os
import shutil
import tempfile

import pytest

from tabx import xla_flags

# One persistent compilation cache (ued/compile_cache.py) for this test session, in a folder of
# its own that starts empty and is deleted at exit: never the user's cache. Ray actors, CLI
# subprocesses and in-process runs load a program that another process compiled instead of
# compiling it again (the Ray tests' actors each compiled the same learner and Explorer
# programs: about half of their time). A loaded program is the one XLA compiled, so results
# are the same bit for bit, and tabx.compile_counter counts a load as a compilation, so the
# no-recompile tests count the same. tests/ued/test_compile_cache.py points the cache at folders
# of its own.
# The suite runs in two pytest-xdist worker processes (pyproject.toml): the controller makes
# the folder, and its workers, which inherit its environment, share it.
_SESSION_CACHE = "TABX_TEST_SESSION_COMPILE_CACHE"
if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get(_SESSION_CACHE):
    _COMPILE_CACHE = os.environ[_SESSION_CACHE]
else:
    _COMPILE_CACHE = tempfile.mkdtemp(prefix="tabx-test-xla-")
    atexit.register(shutil.rmtree, _COMPILE_CACHE, ignore_errors=True)
    os.environ[_SESSION_CACHE] = _COMPILE_CACHE
os.environ["TABX_COMPILE_CACHE_DIR"] = _COMPILE_CACHE

# Two CPU devices on every machine, whatever its core count (the `tabx` command makes one per
# core, see tabx/xla_flags.py), so the data-parallel learner path is tested the same way
# everywhere; then the command's other XLA settings, as its processes run. Set before JAX starts
# its backend; a flag the user set wins.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_force_host_platform_device_count=2").strip()
xla_flags.apply()

# The test session compiles for compile time, not run time: LLVM at optimisation level 0 and
# XLA:CPU's loop emitters (tabx/jit_options.py) compile the tiny learner update about 2.5x faster
# (20 s -> 7 s here) and run it about 2x slower, and a test's programs are compiled far more
# often than they run. Neither option changes what a program computes (no fast-math); results
# are compared only between programs of the same session. Programs whose jit names these options
# itself keep its choice. TABX_TEST_DEFAULT_COMPILER=1 tests with XLA's settings instead.
OPTIMIZING_COMPILER_OPTIONS = {"xla_backend_optimization_level": 3,
                               "xla_cpu_use_fusion_emitters": True}
_QUICK_COMPILE_FLAGS = ("--xla_backend_optimization_level=0",
                        "--xla_cpu_use_fusion_emitters=false")
if os.environ.get("TABX_TEST_DEFAULT_COMPILER") != "1":
    _flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = " ".join(
        [_flags, *(flag for flag in _QUICK_COMPILE_FLAGS if flag.split("=")[0] not in _flags)]
    ).strip()

# Ray clusters in tests live on 127.0.0.1 (read when Ray is imported): without this Ray swaps
# 127.0.0.1 for the machine's outward address and a joining process cannot find the head.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


@pytest.fixture(scope="module")
def local_ray():
    """A Ray of the module's own, three logical CPUs on any machine (a learner and two
    Explorers each reserve one); "local": never a `ray start` cluster whose address another
    test left in /tmp/ray. The Ray test modules use it for all their tests."""
    import ray

    ray.init(address="local", num_cpus=3, include_dashboard=False,
             object_store_memory=128 * 2**20, logging_level="ERROR")
    yield ray
    ray.shutdown()


@pytest.fixture
def optimizing_compiler(monkeypatch):
    """For a test that runs its learner for many updates: its learner programs are compiled
    with XLA's optimisations after all (the session's quick-compile flags above halve the
    speed of a compiled update, which such a test pays on every update)."""
    from tabx import jit_options

    for option, value in OPTIMIZING_COMPILER_OPTIONS.items():
        monkeypatch.setitem(jit_options.LEARNER_CPU_OPTIONS, option, value)


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto`: one worker per core, at most 4 (each worker holds a JAX process, and the Ray
    test modules a Ray of 3 CPUs each)."""
    return max(1, min(os.cpu_count() or 1, 4))


# The files that take longest, longest first (`pytest --durations=0`, summed per file): each
# worker takes the next file when it is done, so starting these first leaves short files to
# fill the end instead of one worker running a long file alone while the other waits.
LONGEST_FILES = ("test_ray_async.py", "test_ray_driver.py", "test_ray_cluster.py",
                 "test_sweep.py", "test_ray_bench.py", "test_learners_learning.py", "test_rnd.py",
                 "test_train_cli.py", "test_fuzz_inputs.py", "test_learners.py",
                 "test_learner_group.py", "test_ued_train.py", "test_kill_resume.py")


def pytest_collection_modifyitems(config, items) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
