"""The XLA:CPU settings of the `tabx` command, for any process to apply before JAX starts its
backend:

    from tabx import xla_flags
    xla_flags.apply()  # before the first JAX computation (XLA reads XLA_FLAGS then)
    import jax

Importing `tabx` applies nothing; the `tabx` command (`tabx_ued.cli.main`), the Ray actors
(`workers.ray.actors`), the profiler's child process and the test session call `apply()`.

1. On jaxlib 0.10 the CPU compiler routes small reductions through its experimental YNN
   fusion, which is 1.5-2x slower for the (envs, units, units) reductions of this simulator
   (docs/benchmarks.md, "Simulator step"): we turn it off.
2. One CPU device per usable core (`--xla_force_host_platform_device_count`), so that a
   learner can split its envs over the cores as data-parallel shards (ued/learners/ppo/train.py
   `learner_devices`): an update is a long chain of small kernels that one device runs on
   about 1.25 cores, while two devices with half the envs each run side by side (IPPO on
   crossfire 1.3x faster on 2 cores, docs/learners_internals.md, "Data parallel over devices").
   Programs that do not ask for the other devices run on the first one, as fast as on a
   single device. Only affects JAX's CPU platform.

Each flag is added to XLA_FLAGS only when the user has not set it, only for jaxlib versions
known to accept it (an unknown XLA flag aborts the process), and never when
TABX_KEEP_XLA_FLAGS=1. Once JAX's backend exists, a change has no effect.
"""

from __future__ import annotations

import os

_YNN_FLAG = "xla_cpu_experimental_ynn_fusion_type"
_DEVICES_FLAG = "xla_force_host_platform_device_count"
_KNOWN_JAXLIB_PREFIXES = ("0.10.",)


def jaxlib_is_measured() -> bool:
    """The installed jaxlib is one our XLA:CPU settings were measured on (and known to accept:
    an unknown XLA option is an error). Also used by `tabx.jit_options`."""
    try:
        from importlib.metadata import version

        jaxlib_version = version("jaxlib")
    except Exception:  # noqa: BLE001 - no metadata: assume not
        return False
    return jaxlib_version.startswith(_KNOWN_JAXLIB_PREFIXES)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def apply() -> bool:
    """Add the flags allowed (see the module doc) to the XLA_FLAGS environment variable;
    return True if it was changed."""
    if os.environ.get("TABX_KEEP_XLA_FLAGS") == "1" or not jaxlib_is_measured():
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    added = []
    if _YNN_FLAG not in flags:
        added.append(f"--{_YNN_FLAG}=")
    cores = usable_cores()
    if _DEVICES_FLAG not in flags and cores > 1:
        added.append(f"--{_DEVICES_FLAG}={cores}")
    if not added:
        return False
    os.environ["XLA_FLAGS"] = " ".join([flags, *added]).strip()
    return True


def match_devices_to_cores() -> bool:
    """After this process's CPU affinity changed (a learner group member pinned to its share
    of the cores) and before JAX starts its backend: one CPU device per core it may now use,
    replacing the count `apply` set. Returns True if XLA_FLAGS changed."""
    if os.environ.get("TABX_KEEP_XLA_FLAGS") == "1" or not jaxlib_is_measured():
        return False
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split() if _DEVICES_FLAG not in f]
    cores = usable_cores()
    flags = " ".join(kept + ([f"--{_DEVICES_FLAG}={cores}"] if cores > 1 else []))
    changed = flags != os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = flags
    return changed


__all__ = ["apply", "jaxlib_is_measured", "match_devices_to_cores", "usable_cores"]
